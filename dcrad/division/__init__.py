"""Divide and conquer: partition, virtual boundaries and twin buffers, subscenes and the barrier loop."""
