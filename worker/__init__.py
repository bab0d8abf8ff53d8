"""The dcrad worker: a gRPC service that holds subscenes and iterates them."""
