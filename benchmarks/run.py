"""Run jaxquat's benchmark suite: `python benchmarks/run.py [--preset quick|full] [--output DIR]`.

A thin wrapper around `jaxquat._bench.main` (the same as `python -m jaxquat bench`); see
`benchmarks/README.md`.
"""

import sys

from jaxquat._bench import main, relaunch_with_huge_pages

if __name__ == "__main__":
    relaunch_with_huge_pages([__file__, *sys.argv[1:]])
    sys.exit(main(sys.argv[1:]))
