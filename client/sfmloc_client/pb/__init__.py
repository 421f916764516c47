"""Generated protobuf/gRPC code for the sfmloc v1 API. Do not edit: run
`make proto` (proto/generate.py)."""
