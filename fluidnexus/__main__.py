"""`python -m fluidnexus`: the same command line as the `fluidnexus` script, for a checkout that
is run from its own folder (PYTHONPATH) rather than installed."""

from fluidnexus.cli import main

main()
