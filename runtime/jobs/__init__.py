"""What the loop runs each cycle: the planner jobs (DWA, SafeMove) and teleoperation."""
