"""Measuring a policy: the validation loss and sampled-chunk error during training
(`validation`), offline evaluation on held-out windows (`offline`), and latency (`latency`)."""
