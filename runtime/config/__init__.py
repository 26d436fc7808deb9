"""The runtime's settings: the schema machinery, the calibration file, the config tree."""
