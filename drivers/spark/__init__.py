"""The Spark base: wire protocol, feedback conversion, the pyserial link."""
