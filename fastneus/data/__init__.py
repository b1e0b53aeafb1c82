"""fastneus.data"""
