"""Readers and writers for formats researchers already have (ActiveNeuS, OpenCV calibration, NeuS)."""
