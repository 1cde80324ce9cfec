"""Engine layer: trainer loop, optimizers and schedules, checkpoints, evaluation, logs."""
