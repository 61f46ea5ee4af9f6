"""fluidcore: the science of FluidNexus (simulation, splatting, reconstruction, prediction).

No web code lives here and nothing is imported from `api` or `worker`. Every tensor
function takes its device from its inputs (or a `device` parameter), so the same code
runs on CPU and CUDA.
"""

__version__ = "0.1.0"
