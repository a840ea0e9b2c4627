"""The walls as the solvers see them, in one place: the signed distance field (stages.common.sdf) and,
precomputed from it, the wall terms of the seed method (Harada et al. 2007, eq. 11-16).

    tables.py   1D flat-wall tables by wall distance (lattice sums over the wall particles of eq. 12, 15)
    maps.py     3D wall maps (Poly6 / Spiky quadrature over the wall region), dense or bricked, their
                sampler (``wall_sample``, ``wall_density``) and the ``Walls`` bundle the WCSPH kernels take
    spline.py   the same maps with DFSPH's cubic spline
    mps.py      MPS's wall sums (number density, gradient, Laplacian channels)

Every map is node-centred at l0/2 over an SDF box, stored as ``wmap`` (dense array or bricks) with
``origin``, ``spacing``, the flat-wall factors ``fix_*`` and ``inv_dr`` of its tables."""
