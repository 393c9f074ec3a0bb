"""`python -m multirace.league worker`: the entry point of league worker processes."""
import sys

from .worker import worker_main

if sys.argv[1:2] == ["worker"]:
    sys.exit(worker_main())
print("usage: python -m multirace.league worker", file=sys.stderr)
sys.exit(2)
