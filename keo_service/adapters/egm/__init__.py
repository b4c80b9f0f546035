"""ABB's Externally Guided Motion message definitions: `egm.proto` as ABB publishes it (with
abb_libegm, BSD-3-Clause, see LICENSE here) and the Python module protoc generated from it.

`egm_pb2.py` is generated, not written: regenerate with

    python -m grpc_tools.protoc -I adapters/egm --python_out=adapters/egm adapters/egm/egm.proto

(generated with grpcio-tools 1.85.1, libprotoc 35.1: protobuf Python gencode 7.35.1, which
needs the protobuf runtime >= 7.35.1 and < 8, as pinned in pyproject.toml).
"""
