"""Generated gRPC/protobuf code for proto/dcrad/v1 (do not edit; `make proto`)."""
