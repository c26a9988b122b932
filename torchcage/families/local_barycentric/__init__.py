"""Local barycentric coordinates, solved by ADMM on a mesh of the cage interior: ``api`` and
``module``."""
