"""`python -m dider.bench`: the benchmark's command line (:mod:`dider.bench`)."""

from dider.bench.cli import main

if __name__ == "__main__":
    main()
