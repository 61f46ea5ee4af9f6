"""fluidcore: the science of FluidNexus (simulation, splatting, reconstruction, prediction).

No web code lives here and nothing is imported from `api` or `worker`. Every tensor
function takes its device from its inputs (or a `device` parameter), so the same code
runs on CPU and CUDA.
"""

import os

# OpenMP threads wait passively unless the environment says otherwise. A worker shares its
# cores with the API, torch's thread pool and other workers; spinning threads that lose their
# core stall every barrier (the 2-thread physics step ran 2x slower spinning than waiting
# passively on a loaded 2-core machine). The runtime reads this once, when torch first loads
# it, so it is set here, before any fluidcore module imports torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
