"""The `hostd` command.

For now it only knows its version; `serve` and the client commands of
../shared/spec/running.md arrive with the daemon and API issues.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from hostd import __version__


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="hostd", description="Host daemon for g2core CNC and laser controllers."
    )
    parser.add_argument("--version", action="version", version=f"hostd {__version__}")
    parser.parse_args(argv)
    parser.print_help(sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
