"""fastneus.export"""
