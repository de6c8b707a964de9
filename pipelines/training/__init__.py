"""The loop and what runs inside it.

    run.py           a run's lifecycle around the loop: open or resume a run directory, summary, disk-full handling
                     (``Run.session``)
    loop.py          collect, update, then the triggers; their final firing at the end (``Loop``)
    context.py       what a trigger may use of the running loop (``LoopContext``) and the live log
    triggers.py      log, eval, export, checkpoint, video: each does its own work (``Trigger``, ``IntervalTrigger``)
    evaluations.py   the eval trigger's evaluations: here, in a process, on a Ray actor; the random baseline
    state.py         where a run is (counters, owed triggers, pending evaluations) and the triggers' names
    resume.py        what else a checkpoint needs for a resumed run to equal an uninterrupted one (``ExactResume``)
    rate_limiter.py  updates per frame (TF-Agents' SampleToInsertRatio)
    nstep.py         n-step transitions (``n_step``), made from each collected block before it is stored
    meters.py        training time, speeds, losses, episode returns between two log rows
    divergence.py    the check that stops a run whose loss or parameters turned NaN or infinite
    faults.py        the loop's fault points for the tests, pressed by a trigger (``RLPIPE_FAULT``; system/faults.py)
    determinism.py   what decides a run's float arithmetic, recorded to tell an exact resume from one that is not
    live_report.py   the run's report.html and returns.png as the run writes them
    threads.py       the learner's torch threads (``num_threads=-1``)
    update_graph.py  the update replayed as CUDA graphs
"""
