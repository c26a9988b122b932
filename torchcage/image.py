r"""Differentiable image warping with 2D cages, sampled through kornia.

**Pixel convention.** Pixel ``(row, col)`` of an ``(H, W)`` image has its centre at ``x = col``,
``y = row`` (pixel units, origin at the centre of the top-left pixel, ``y`` pointing down). Cage
vertices are given in the same ``(x, y)`` pixel coordinates. This is kornia's ``remap`` convention
with ``align_corners=True`` (``x`` in ``[0, W - 1]`` spans the image), which torchcage passes;
kornia's default (``None``, meaning ``False``) would shift an identity map by up to 0.7 pixels.
Because ``y`` points down, a polygon that looks counter-clockwise on screen is clockwise in these
coordinates: torchcage orients it by itself, without changing the vertex order.

**Two mappings** give the colour of output pixel ``y`` for a deformed cage ``C'``:

- ``"backward"`` (exact by definition): the coordinates of ``y`` with respect to the *deformed* cage
  map it back into the rest cage, ``x = sum_i w_i(y; C') v_i`` (mean value), or Green's formula with
  the deformed cage as the rest one; the output samples the source image at ``x``. The coordinates
  are computed for every pose (about 0.1 s per 512x512 pose with the native kernel), and gradients
  with respect to the vertices flow through the torch kernel, which is slower and needs memory
  proportional to pixels x cage edges.
- ``"forward"`` (fast with a fixed output grid): the coordinates of the source pixel centres with
  respect to the rest cage are computed once; a pose moves this pixel mesh with one matrix product
  (``f(x) = sum_i w_i(x) v'_i``, the same deformation as :class:`torchcage.MeanValueCoordinates` and
  friends apply to points) and the moved mesh is rasterised onto the output grid: output pixel
  ``y`` samples the source at the preimage ``f_h^{-1}(y)`` of the piecewise-linear interpolant
  ``f_h`` of ``f`` on the pixel mesh. It is exact for affine cage motions and accurate to the
  second-order variation of ``f`` across one pixel otherwise; gradients flow to the vertices
  through the barycentric coordinates of each pixel in its moved triangle. A two-pixel band of
  mesh vertices outside the rest cage is extrapolated linearly (which keeps linear precision) so
  that the moved mesh covers the whole deformed cage.

The two mappings agree exactly for affine cage motions (linear precision) and differ otherwise:
the backward mapping inverts the deformation *defined by the deformed cage*, the forward mapping
inverts the deformation the modules apply to points. Local barycentric coordinates are computed
once by an iterative solver, so ``method="lbc"`` supports only the forward mapping.

Pixels outside the deformed cage are handled by ``outside=``: ``"keep"`` shows the source image
there unchanged, ``"zero"`` writes zeros, ``"mask"`` writes zeros and also returns the boolean mask
of pixels inside the deformed cage.
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import nn

from torchcage._raster import rasterize_triangles
from torchcage.cage import Cage
from torchcage.errors import CageError
from torchcage.families import family
from torchcage.families.green.api import green_coordinates
from torchcage.families.green.stretch import stretched_normals
from torchcage.families.mean_value.api import mean_value_coordinates
from torchcage.geometry import inside_polygon

__all__ = ["CageWarp", "inside_polygon", "pixel_centres", "warp_image"]

#: The families that warp images (``"green"`` is a deprecated alias of ``"gc"``).
METHODS = ("mvc", "gc", "lbc")
MAPPINGS = ("forward", "backward")
OUTSIDE = ("keep", "zero", "mask")
MODES = ("bilinear", "nearest")
#: Rings of pixels outside the rest cage whose coordinates are extrapolated for the forward mapping.
BAND = 2


def _kornia_remap() -> Any:
    try:
        from kornia.geometry.transform import remap
    except ImportError as err:  # pragma: no cover - exercised only without kornia
        raise ImportError(
            "torchcage.image samples images with kornia; install it with `pip install torchcage[image]` "
            "(or `pip install kornia`)"
        ) from err
    return remap


def pixel_centres(
    height: int, width: int, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> torch.Tensor:
    """Centres ``(x, y) = (col, row)`` of an image's pixels in row-major order.

    Returns:
        ``(H * W, 2)`` coordinates.

    Examples:
        >>> pixel_centres(2, 3)[:4]
        tensor([[0., 0.],
                [1., 0.],
                [2., 0.],
                [0., 1.]], dtype=torch.float64)
    """
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device), torch.arange(width, dtype=dtype, device=device), indexing="ij"
    )
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1)


def _as_cage(cage: Cage | torch.Tensor) -> Cage:
    """A 2D Cage from a Cage or a ``(V, 2)`` polygon (oriented silently: image polygons are often
    drawn clockwise in y-down coordinates)."""
    if isinstance(cage, Cage):
        if cage.dim != 2:
            raise CageError(f"image warping needs a 2D cage (a polygon), got a {cage.dim}D cage")
        return cage
    v = torch.as_tensor(cage)
    if v.ndim != 2 or v.shape[1] != 2:
        raise CageError(f"a polygon cage must be a Cage or a (V, 2) tensor of vertices, got shape {tuple(v.shape)}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Cage(v.to(torch.float64) if not v.is_floating_point() else v)


def _coordinates(points: torch.Tensor, cage: Cage, method: str, options: dict[str, Any]) -> torch.Tensor:
    """Rows ``(N, K)`` that map the method's basis (vertices, then stretched normals for Green) to
    deformed positions."""
    if method == "mvc":
        return mean_value_coordinates(points, cage, **options)
    if method == "gc":
        phi, psi = green_coordinates(points, cage, **options)
        return torch.cat([phi, psi], dim=1)
    from torchcage.families.local_barycentric.api import local_barycentric_coordinates

    return local_barycentric_coordinates(points, cage, **options).to_dense()


def _basis(method: str, rest: torch.Tensor, vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``(*, K, 2)``: the deformed vertices, and for Green the stretched deformed normals."""
    if method == "gc":
        return torch.cat([vertices, stretched_normals(rest, vertices, edges)], dim=-2)
    return vertices


def _check_options(method: str, mapping: str, mode: str, outside: str) -> str:
    """The method's short name (an alias warns), once every option is checked."""
    method = family(method, METHODS, stacklevel=3).short
    for name, value, allowed in (("mapping", mapping, MAPPINGS), ("mode", mode, MODES), ("outside", outside, OUTSIDE)):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
    if method == "lbc" and mapping == "backward":
        raise ValueError(
            "method='lbc' supports only mapping='forward' (local barycentric coordinates come from an "
            "iterative solve on the rest cage, too costly to repeat for every deformed cage)"
        )
    return method


def _forward_mesh(
    cage: Cage, height: int, width: int, method: str, options: dict[str, Any], dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pixel mesh of the forward mapping.

    Returns:
        ``weights (Nv, K)`` rows of the mesh vertices, ``pixels (Nv,)`` their flat pixel indices,
        ``triangles (T, 3)`` in mesh-vertex indices, ``interior (T,)`` triangles with all three
        corners inside the rest cage.
    """
    dev = cage.device
    pts = pixel_centres(height, width, dtype=dtype, device=dev)
    inside = inside_polygon(pts, cage.vertices.to(dtype), cage.edges).reshape(height, width)
    if not bool(inside.any()):
        raise CageError(f"the cage holds no pixel centre of the {height}x{width} grid; give it in pixel coordinates")
    rows = _coordinates(pts[inside.reshape(-1)], cage, method, options)
    grid = torch.zeros((height * width, rows.shape[1]), dtype=rows.dtype, device=dev)
    grid[inside.reshape(-1)] = rows
    valid = inside.clone()
    rr, cc = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev), indexing="ij")
    for _ in range(BAND):
        # Linear extrapolation along an axis, W(x) = 2 W(x + e) - W(x + 2 e): reproduces constants
        # and linear functions, so the band keeps the coordinates' linear precision.
        new = torch.zeros_like(valid)
        for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            r2, c2 = rr + 2 * dr, cc + 2 * dc
            fits = (r2 >= 0) & (r2 < height) & (c2 >= 0) & (c2 < width)
            near = torch.zeros_like(valid)
            far = torch.zeros_like(valid)
            near[fits] = valid[(rr + dr)[fits], (cc + dc)[fits]]
            far[fits] = valid[r2[fits], c2[fits]]
            cand = torch.nonzero((~valid & ~new & near & far).reshape(-1)).squeeze(1)
            if cand.numel():
                step = dr * width + dc
                grid[cand] = 2 * grid[cand + step] - grid[cand + 2 * step]
                new.view(-1)[cand] = True
        valid |= new
    flat_valid = valid.reshape(-1)
    pixels = torch.nonzero(flat_valid).squeeze(1)
    weights = grid[pixels]
    compact = torch.full((height * width,), -1, dtype=torch.int64, device=dev)
    compact[pixels] = torch.arange(pixels.shape[0], device=dev)
    # Two triangles per cell (top-left, top-right, bottom-left, bottom-right corners), kept when
    # all their corners are mesh vertices.
    r, c = torch.meshgrid(torch.arange(height - 1, device=dev), torch.arange(width - 1, device=dev), indexing="ij")
    tl = (r * width + c).reshape(-1)
    tr, bl, br = tl + 1, tl + width, tl + width + 1
    tris = torch.cat([torch.stack([tl, tr, bl], 1), torch.stack([tr, br, bl], 1)])
    tris = tris[flat_valid[tris].all(dim=1)]
    interior = inside.reshape(-1)[tris].all(dim=1)
    return weights, pixels, compact[tris], interior


class CageWarp(nn.Module):
    """Warp images with a 2D cage, batched over images and deformed cages.

    With ``mapping="forward"`` (the default) the coordinates of the source pixel grid are computed
    once (buffers ``weights``, ``mesh_pixels``, ``mesh_triangles``, ``interior``, saved in the
    ``state_dict``) and each pose costs one matrix product, a rasterisation and a sampling; with
    ``mapping="backward"`` each pose's coordinates are computed on the fly (see the module's
    docstring for which is exact for what).

    Args:
        cage: a 2D :class:`torchcage.Cage` or a ``(V, 2)`` polygon, in pixel coordinates.
        height: image rows ``H``.
        width: image columns ``W``.
        method: ``"mvc"`` (mean value), ``"gc"`` (Green, conformal; ``"green"`` is a deprecated
            alias) or ``"lbc"`` (local barycentric,
            forward mapping only; ``lbc_options`` are passed to
            :func:`torchcage.functional.local_barycentric_coordinates`).
        mapping: ``"forward"`` (default here) or ``"backward"``. The defaults differ on purpose:
            a module is built to warp many poses, and the forward mapping computes its
            coordinates once; :func:`warp_image` warps one pose, where the backward mapping costs
            the same and is exact (it inverts the deformation the deformed cage defines).
        mode: ``"bilinear"`` or ``"nearest"`` sampling.
        outside: ``"keep"``, ``"zero"`` or ``"mask"`` for pixels outside the deformed cage.
        dtype: dtype of the stored coordinates (float64 by default).
        lbc_options: keyword arguments for the LBC solve.

    Shape:
        - Input: ``image (B, C, H, W)`` or ``(C, H, W)``; ``vertices (B, V, 2)`` or ``(V, 2)``
          (batch sizes broadcast).
        - Output: the warped images ``(B, C, H, W)`` (``(C, H, W)`` when both inputs are unbatched);
          with ``outside="mask"`` also ``mask (B, 1, H, W)`` bool.

    Examples:
        >>> import torch
        >>> from torchcage.image import CageWarp
        >>> cage = torch.tensor([[4.0, 4], [27, 4], [27, 27], [4, 27]], dtype=torch.float64)
        >>> warp = CageWarp(cage, 32, 32)
        >>> img = torch.rand(1, 3, 32, 32, dtype=torch.float64)
        >>> torch.allclose(warp(img, cage), img)                   # the rest cage changes nothing
        True
        >>> out = warp(img, cage + torch.tensor([3.0, 0.0], dtype=torch.float64))
        >>> torch.allclose(out[..., 10:20, 10:20], img[..., 10:20, 7:17])   # shifted by 3 columns
        True
    """

    rest_vertices: torch.Tensor
    edges: torch.Tensor
    weights: torch.Tensor
    mesh_pixels: torch.Tensor
    mesh_triangles: torch.Tensor
    interior: torch.Tensor

    def __init__(
        self,
        cage: Cage | torch.Tensor,
        height: int,
        width: int,
        *,
        method: str = "mvc",
        mapping: str = "forward",
        mode: str = "bilinear",
        outside: str = "keep",
        dtype: torch.dtype = torch.float64,
        lbc_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        method = _check_options(method, mapping, mode, outside)
        if height < 2 or width < 2:
            raise ValueError(f"images must be at least 2x2 pixels, got {height}x{width}")
        cage = _as_cage(cage)
        self.height, self.width = int(height), int(width)
        self.method, self.mapping, self.mode, self.outside = method, mapping, mode, outside
        self.register_buffer("rest_vertices", cage.vertices.detach().clone())
        self.register_buffer("edges", cage.edges.clone())
        if mapping == "forward":
            options: dict[str, Any] = dict(lbc_options or {}) if method == "lbc" else {}
            w, pix, tris, interior = _forward_mesh(cage, self.height, self.width, method, options, torch.float64)
            self.register_buffer("weights", w.to(dtype))
            self.register_buffer("mesh_pixels", pix)
            self.register_buffer("mesh_triangles", tris)
            self.register_buffer("interior", interior)

    def extra_repr(self) -> str:
        return (
            f"{self.height}x{self.width}, method={self.method!r}, mapping={self.mapping!r}, mode={self.mode!r}, "
            f"outside={self.outside!r}, cage_vertices={self.rest_vertices.shape[0]}"
        )

    def _check(self, vertices: torch.Tensor) -> torch.Tensor:
        if not isinstance(vertices, torch.Tensor) or not vertices.is_floating_point():
            raise TypeError("vertices must be a floating-point tensor of shape (B, V, 2) or (V, 2)")
        V = self.rest_vertices.shape[0]
        if vertices.ndim not in (2, 3) or tuple(vertices.shape[-2:]) != (V, 2):
            raise ValueError(f"vertices must have shape (B, {V}, 2) or ({V}, 2), got {tuple(vertices.shape)}")
        if vertices.device != self.rest_vertices.device:
            raise ValueError(
                f"vertices are on {vertices.device} but the warp's buffers are on {self.rest_vertices.device}; "
                "call warp.to(device) or move the vertices"
            )
        if not bool(torch.isfinite(vertices).all()):
            raise ValueError("vertices contain NaN or inf")
        return vertices if vertices.ndim == 3 else vertices[None]

    def sampling_grid(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Source coordinates of every output pixel for deformed cages.

        Args:
            vertices: ``(B, V, 2)`` or ``(V, 2)`` deformed cage vertices (pixel coordinates).

        Returns:
            ``grid (B, H, W, 2)``: the source ``(x, y)`` each output pixel samples (the pixel's own
            centre outside the deformed cage), differentiable with respect to ``vertices``; and
            ``inside (B, H, W)`` bool.
        """
        verts = self._check(vertices)
        if self.mapping == "forward":
            return self._forward_grid(verts)
        return self._backward_grid(verts)

    def _forward_grid(self, verts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        H, W = self.height, self.width
        dt = verts.dtype
        basis = _basis(self.method, self.rest_vertices.to(dt), verts, self.edges)  # (B, K, 2)
        moved = torch.matmul(self.weights.to(dt), basis)  # (B, Nv, 2)
        B, Nv = verts.shape[0], moved.shape[1]
        centres = pixel_centres(H, W, dtype=dt, device=verts.device)
        src = centres.index_select(0, self.mesh_pixels)  # (Nv, 2) source pixel centres of the mesh
        which, val = rasterize_triangles(moved, self.mesh_triangles, H, W, src)
        which = which.reshape(-1)  # (B * H * W,)
        covered = which >= 0
        t = which.clamp_min(0)
        y = centres.repeat(B, 1)
        x = val.reshape(-1, 2).to(dt)
        if torch.is_grad_enabled() and moved.requires_grad:
            # Recompute the covered pixels' barycentric coordinates in their moved triangles with
            # torch ops, so that gradients reach the vertices (flat index_select: several times
            # faster than advanced indexing here).
            idx = torch.nonzero(covered).squeeze(1)
            tri = self.mesh_triangles.index_select(0, t.index_select(0, idx))
            offset = (idx // (H * W)) * Nv
            flat = moved.reshape(-1, 2)
            a, b, c = (flat.index_select(0, tri[:, k] + offset) for k in range(3))
            u, v, d = b - a, c - a, y.index_select(0, idx) - a
            det = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
            l1 = (d[:, 0] * v[:, 1] - d[:, 1] * v[:, 0]) / det
            l2 = (u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0]) / det
            s0, s1, s2 = (src.index_select(0, tri[:, k]) for k in range(3))
            x = x.index_put((idx,), s0 + l1[:, None] * (s1 - s0) + l2[:, None] * (s2 - s0))
        # A covered pixel is inside the deformed cage when its preimage is inside the rest cage:
        # certain for triangles with all corners inside, tested exactly in the band.
        ok = covered & self.interior.index_select(0, t)
        band = torch.nonzero(covered & ~ok).squeeze(1)
        if band.numel():
            ok[band] = inside_polygon(x[band].detach(), self.rest_vertices.to(dt), self.edges)
        grid = torch.where(ok[:, None], x, y)
        return grid.reshape(B, H, W, 2), ok.reshape(B, H, W)

    def _backward_grid(self, verts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        H, W = self.height, self.width
        dt = verts.dtype
        centres = pixel_centres(H, W, dtype=dt, device=verts.device)
        rest = self.rest_vertices.to(dt)
        grids, insides = [], []
        for pose in verts:  # one coordinate computation per deformed cage
            inside = inside_polygon(centres, pose.detach(), self.edges)
            y = centres[inside]
            deformed = Cage._from_faces(pose, self.edges)
            if self.method == "mvc":
                x = mean_value_coordinates(y, deformed) @ rest
            else:  # green: the deformed cage plays the rest cage's part, stretch |a| / |a'|
                phi, psi = green_coordinates(y, deformed)
                x = phi @ rest + psi @ stretched_normals(pose, rest, self.edges)
            grid = centres.clone().index_put((torch.nonzero(inside).squeeze(1),), x)
            grids.append(grid.reshape(H, W, 2))
            insides.append(inside.reshape(H, W))
        return torch.stack(grids), torch.stack(insides)

    def forward(self, image: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Warp ``image`` for the deformed cage(s) ``vertices`` (see the class docstring for shapes)."""
        if not isinstance(image, torch.Tensor) or not image.is_floating_point():
            raise TypeError("image must be a floating-point tensor of shape (B, C, H, W) or (C, H, W)")
        unbatched = image.ndim == 3 and vertices.ndim == 2
        img = image[None] if image.ndim == 3 else image
        if img.ndim != 4 or tuple(img.shape[-2:]) != (self.height, self.width):
            raise ValueError(
                f"image must have shape (B, C, {self.height}, {self.width}) or (C, {self.height}, {self.width}) "
                f"for this warp, got {tuple(image.shape)}"
            )
        if img.device != self.rest_vertices.device:
            raise ValueError(f"image is on {img.device} but the warp's buffers are on {self.rest_vertices.device}")
        grid, inside = self.sampling_grid(vertices)
        B = max(img.shape[0], grid.shape[0])
        if img.shape[0] not in (1, B) or grid.shape[0] not in (1, B):
            raise ValueError(f"batch sizes of image ({img.shape[0]}) and vertices ({grid.shape[0]}) do not broadcast")
        img, grid, inside = img.expand(B, -1, -1, -1), grid.expand(B, -1, -1, -1), inside.expand(B, -1, -1)
        grid = grid.to(img.dtype)
        out = _kornia_remap()(img, grid[..., 0], grid[..., 1], mode=self.mode, padding_mode="zeros", align_corners=True)
        mask = inside[:, None]
        out = torch.where(mask, out, img if self.outside == "keep" else torch.zeros((), dtype=out.dtype))
        if unbatched:
            out, mask = out[0], mask[0]
        return (out, mask) if self.outside == "mask" else out


def warp_image(
    image: torch.Tensor,
    cage: Cage | torch.Tensor,
    vertices: torch.Tensor,
    *,
    method: str = "mvc",
    mapping: str = "backward",
    mode: str = "bilinear",
    outside: str = "keep",
    lbc_options: dict[str, Any] | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Warp images by moving the vertices of a 2D cage drawn over them (one-shot form of
    :class:`CageWarp`; build the module to reuse precomputed coordinates across calls).

    Args:
        image: ``(B, C, H, W)`` or ``(C, H, W)`` images.
        cage: the rest cage, a 2D :class:`torchcage.Cage` or a ``(V, 2)`` polygon, in pixel
            coordinates ``(x, y) = (col, row)``.
        vertices: ``(B, V, 2)`` or ``(V, 2)`` deformed cage vertices.
        method: ``"mvc"``, ``"gc"`` (``"green"``: a deprecated alias) or ``"lbc"`` (forward
            mapping only).
        mapping: ``"backward"`` (default here) or ``"forward"``. The defaults differ on purpose:
            one call warps one pose, where the backward mapping (coordinates of the output pixels
            in the deformed cage, computed per pose) costs the same as the forward one and is
            exact; :class:`CageWarp` defaults to ``"forward"``, whose coordinates are computed
            once for all the poses a module warps.
        mode: ``"bilinear"`` or ``"nearest"``.
        outside: ``"keep"``, ``"zero"`` or ``"mask"`` (then ``(image, mask)`` is returned).
        lbc_options: keyword arguments of the LBC solve for ``method="lbc"``.

    Returns:
        Warped images shaped like the broadcast inputs (and the ``(B, 1, H, W)`` mask for
        ``outside="mask"``). Differentiable with respect to ``image`` and ``vertices``.

    Examples:
        >>> import torch
        >>> from torchcage.image import warp_image
        >>> cage = torch.tensor([[2.0, 2], [13, 2], [13, 13], [2, 13]], dtype=torch.float64)
        >>> img = torch.rand(1, 1, 16, 16, dtype=torch.float64)
        >>> out, mask = warp_image(img, cage, cage * 0.5 + 4, outside="mask")   # shrink about (8, 8)
        >>> bool(mask[0, 0, 8, 8]), bool(mask[0, 0, 1, 1])
        (True, False)
    """
    warp = CageWarp(
        cage, image.shape[-2], image.shape[-1], method=method, mapping=mapping, mode=mode, outside=outside,
        dtype=torch.float64, lbc_options=lbc_options,
    )  # fmt: skip
    return warp.to(image.device)(image, vertices)
