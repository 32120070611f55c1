"""bsdf"""
