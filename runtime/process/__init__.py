"""The process around the pipeline: the control loop, its timing, systemd notification."""
