"""Layer 5: the fit driver that runs the stages on every path, and `c1mesh info`."""
