"""relief-bsdf: optical scattering (BSDF) of a rough boundary from its measured micro-relief.

Data flows one way: relief -> boundary BSDF -> plate -> comparison -> fit / diagnosis
-> export / Blender.  This package is the engine; it never imports bpy.
"""
__version__ = "0.1.0"
