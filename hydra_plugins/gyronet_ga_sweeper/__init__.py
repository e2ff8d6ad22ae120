"""A Hydra sweeper that tunes hyperparameters with a genetic algorithm (``hydra/sweeper=ga``)."""
