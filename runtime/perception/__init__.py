"""Depth frame to world: admission, depth to points and scan, obstacle memory, tracking."""
