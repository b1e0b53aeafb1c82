"""fastneus.eval: evaluation: metrics, depth errors, the report."""
