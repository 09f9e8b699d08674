"""Training, evaluation and prediction: the trainer, checkpoints, distributed runs, run logs, schedules and the
reference frame of the benchmarks."""
