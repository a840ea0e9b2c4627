"""`python -m pipeline ...`: the same command line as the `pipeline` console script."""
from .cli import main

main(prog_name="pipeline")
