"""fastneus.baselines"""
