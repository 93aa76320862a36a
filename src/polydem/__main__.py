"""``python -m polydem`` and the ``polydem`` command (see :mod:`polydem.cli`).

The signal handlers go in before the rest of polydem (numpy, trimesh, scipy, Warp) is imported,
so that a Ctrl-C or SIGTERM in the first second stops the command with one line (exit code 130 or
143) instead of a traceback, or of being swallowed by a library's import. (Before this module's
code runs, while the interpreter itself starts, Python's own handling applies.)
"""

import sys


def main() -> int:
    try:
        from polydem import signals

        signals.install()
    except KeyboardInterrupt:  # before the handlers were in
        sys.stderr.write("polydem: stopped by Ctrl-C; nothing was written\n")
        return 130
    try:
        try:
            from polydem.cli import main as cli_main

            signals.check()
        except KeyboardInterrupt:
            sys.stderr.write(f"polydem: stopped by {signals.name()}; nothing was written\n")
            return signals.exit_code()
        return cli_main()
    finally:
        signals.uninstall()


if __name__ == "__main__":
    sys.exit(main())
