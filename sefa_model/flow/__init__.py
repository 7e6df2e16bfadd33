"""The flow's mathematics: the rectified-flow path and loss, the ODE solvers that sample it,
and CUDA graphs that replay a velocity field. Nothing here imports sefa: plain torch."""
