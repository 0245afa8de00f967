"""Regenerate the Python protobuf modules from the ``.proto`` files in this folder.

Needs ``grpcio-tools`` (a developer dependency, not a runtime one)::

    python -m converters.womd.protos.generate
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    from grpc_tools import protoc  # imported here: only developers need it

    protos = sorted(p.name for p in HERE.glob("*.proto"))
    args = ["protoc", f"-I{HERE}", f"--python_out={HERE}", *protos]
    return protoc.main(args)


if __name__ == "__main__":
    sys.exit(main())
