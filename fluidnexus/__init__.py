"""The `fluidnexus` command line: the front door to fluidcore, the service and the benchmarks."""
