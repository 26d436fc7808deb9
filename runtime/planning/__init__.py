"""Local planning: DWA, track prediction, the safe corridor, stall recovery."""
