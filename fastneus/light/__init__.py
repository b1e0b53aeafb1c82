"""fastneus.light: what projectors emit: pattern generators and decoders, laser planes."""
