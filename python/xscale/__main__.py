"""``python -m xscale <command> …``: the xscale command line, from the installed package
(the same program as the ``xscale`` binary built by cargo; ``python -m xscale --help``)."""

import sys

from . import _xscale


def main() -> int:
    return _xscale._cli(["xscale", *sys.argv[1:]])


if __name__ == "__main__":
    sys.exit(main())
