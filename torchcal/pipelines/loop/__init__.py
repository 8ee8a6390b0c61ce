"""The loop with measured data: calibrate, look at the residual, trace it to a physical effect,
add it, report held-out error before and after."""
from torchcal.pipelines.loop.run import run_loop

__all__ = ["run_loop"]
