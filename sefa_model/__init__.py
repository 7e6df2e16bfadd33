"""sefa_model: networks, flows, solvers, reflow, alignment, distillation and the policy."""
