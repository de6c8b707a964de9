"""The presets rlpipe ships: one YAML file per preset, its name the file's stem (``sac-pendulum.yaml`` is preset
``sac-pendulum``). Data only: ``rlpipe.pipelines.presets`` reads them (``load``, ``names``) and writes a user's own
(``save``); ``rlpipe presets`` lists them, ``rlpipe presets --show NAME`` prints one."""
