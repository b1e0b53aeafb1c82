"""fastneus.classical: classical structured-light decoders: Gray code, plane sweep, laser lines."""
