"""fastneus.synth: synthetic structured-light scenes with ground truth."""
