"""`python -m jaxquat ...`: the command line (see `jaxquat._cli`)."""

try:
    from ._cli import main
except KeyboardInterrupt:  # Ctrl-C while the command line loads: one line and 130, as main() gives
    import os
    import sys

    print("jaxquat: interrupted", file=sys.stderr)
    sys.stderr.flush()
    os._exit(130)  # and no teardown, as after main()'s line (see jaxquat._cli._exit_now)

if __name__ == "__main__":
    raise SystemExit(main())
