"""The operating system's side: stop signals at safe points, the fault-injection hook (``faults``), child
processes, and the memory a run will take against what the machine has."""
