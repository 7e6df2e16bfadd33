"""Training: the loop (`loop`, read top to bottom as nanoGPT's), what each step fits and how
its batch is drawn (`batches`, `device_batches` on CUDA), EMA (`ema`), the run log (`run_log`)
and the limits a batch must respect (`limits`)."""
