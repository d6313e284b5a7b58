"""`python -m jaxquat ...`: the command line (see `jaxquat._cli`)."""

from ._cli import main

if __name__ == "__main__":
    raise SystemExit(main())
