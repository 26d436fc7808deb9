"""The `safemove` command line and the composition root that builds the drivers."""
