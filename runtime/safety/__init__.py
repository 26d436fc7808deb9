"""The safety shield and the limits stage, applied last."""
