"""`python -m benchmarks`: run the benchmark suite (`--list` lists it; `benchmarks/_suite.py`)."""

from benchmarks._suite import main

raise SystemExit(main())
