"""fastneus.field"""
