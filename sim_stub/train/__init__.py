"""Training: the gymnasium environment over the lock-stepped robot and `safemove train`."""
