"""The one training contract (TrainableModule), the train function, run configs, checkpoints, EMA and the optimiser."""
