"""Training, evaluation and prediction: experiments, checkpoints, distributed runs, logs and the demo."""
