"""SeFA's stages after the base flow, in pipeline order: reflow's couplings (`reflow`), then
selective alignment (`alignment`); distillation is a training run of a student method
(`sefa_model.methods`)."""
