"""Volumetric cloth (the paper's Section 5, Eq. 1-3): the fiber BCSDF as a phase function, the
voxelized fibers as an anisotropic medium, and the scene assembly of ``render --cloth``."""
