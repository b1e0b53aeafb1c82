"""fastneus.train"""
