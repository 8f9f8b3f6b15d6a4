"""The ``orientlab`` command (and ``python -m app``): the command line, imported behind a
guard. Importing it loads numpy and compiles or loads the filters' first functions (half a
second and more): a Ctrl-C pressed meanwhile is the same one line as later, not a
30-line traceback."""

from __future__ import annotations

import sys


def run() -> int:
    try:
        from app.cli import main
    except KeyboardInterrupt:
        print("orientlab: interrupted", file=sys.stderr)
        return 130
    return main()


if __name__ == "__main__":
    sys.exit(run())
