"""Rigid indenters: loading meshes in declared units, the parametric library, start poses."""
