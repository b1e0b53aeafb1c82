"""fastneus.synth.render: synthetic structured-light scenes with ground truth."""
