"""The control socket's protocol and config: what the service accepts as goals, shared by the
server (runtime.process) and the mission job (runtime.jobs)."""
