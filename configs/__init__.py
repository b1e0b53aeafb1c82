"""YAML presets shipped with fastneus (installed as ``fastneus.configs``)."""
