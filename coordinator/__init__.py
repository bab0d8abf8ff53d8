"""The dcrad coordinator: jobs, workers, partitions and barriers over gRPC."""
