"""fastneus: fast ActiveNeuS reconstruction from structured-light images."""
__version__ = "0.1.0"
