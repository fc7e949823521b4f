"""Readers and writers at the system's edges: calibration formats, frame sources, PLY."""
