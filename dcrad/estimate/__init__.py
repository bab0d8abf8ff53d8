"""The run's error: the estimate from half-solutions and bias, and comparisons against references."""
