"""What a run leaves on disk: the run directory and its metrics table, checkpoints, the exported
policy, videos, and the atomic, fsynced file writes they share."""
