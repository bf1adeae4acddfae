"""Sparse non-rigid registration (Su et al. 2019 after Yang et al. 2015): pure numpy/scipy.

    result = register(source_xyz, target_xyz, source_rgb, target_rgb, config)
    moved = apply_transforms(result, source_xyz, other_xyz)

Files in pipeline order: graph.py (nodes, neighbour graph, operators D and B),
correspondences.py, rigid.py (pre-alignment), admm.py (the solver), register.py (outer loop);
pair.py (`register_pair`: what `register-pair` runs; robust colour decision in colour.py,
partial overlap in overlap.py).
"""

from .pair import register_pair
from .register import RegistrationResult, apply_transforms, register

__all__ = ["RegistrationResult", "apply_transforms", "register", "register_pair"]
