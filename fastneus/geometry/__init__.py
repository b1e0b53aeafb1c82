"""fastneus.geometry: cameras, rigid transforms and projector projection (pure maths on tensors/arrays)."""
