"""Render layer: gsplat-compatible ``rasterization()`` with reference (torch), cpu (compiled) and gsplat backends."""
