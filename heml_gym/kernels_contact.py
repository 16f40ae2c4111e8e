"""Numba kernels of the rigid support surfaces: signed distances and the projection of a
vertex out of them.

Supports reach the kernels as plain arrays (see :class:`heml_gym.contact.Supports`):

* ``planes (P, 4)``: unit normal ``n`` and offset ``c`` of each half-space
  ``n . x >= c`` the tissue must stay in (m);
* ``grids (G, 8)``: per signed-distance grid its origin (m), spacing (m), node counts
  along x, y, z and the start of its values in ``grid_values``;
* ``grid_values``: the grids' signed distances at their nodes (m, negative inside),
  x-major then y then z.

A vertex found inside a support is moved to its surface along the normal and loses
the velocity component into it (a rigid, frictionless, perfectly inelastic contact).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def grid_signed_distance(grids, grid_values, g, px, py, pz):
    """Trilinear signed distance (m) of ``p`` to grid ``g`` and its gradient.

    Returns ``(d, gx, gy, gz)``; ``d = inf`` outside the grid's box.
    """
    ox = grids[g, 0]
    oy = grids[g, 1]
    oz = grids[g, 2]
    h = grids[g, 3]
    nx = int(grids[g, 4])
    ny = int(grids[g, 5])
    nz = int(grids[g, 6])
    start = int(grids[g, 7])
    fx = (px - ox) / h
    fy = (py - oy) / h
    fz = (pz - oz) / h
    if not (fx >= 0.0 and fy >= 0.0 and fz >= 0.0 and fx <= nx - 1 and fy <= ny - 1 and fz <= nz - 1):
        return math.inf, 0.0, 0.0, 0.0
    i = min(int(fx), nx - 2)
    j = min(int(fy), ny - 2)
    k = min(int(fz), nz - 2)
    tx = fx - i
    ty = fy - j
    tz = fz - k
    base = start + (i * ny + j) * nz + k
    sy = nz
    sx = ny * nz
    c000 = grid_values[base]
    c001 = grid_values[base + 1]
    c010 = grid_values[base + sy]
    c011 = grid_values[base + sy + 1]
    c100 = grid_values[base + sx]
    c101 = grid_values[base + sx + 1]
    c110 = grid_values[base + sx + sy]
    c111 = grid_values[base + sx + sy + 1]
    # interpolate along z, then y, then x
    c00 = c000 + tz * (c001 - c000)
    c01 = c010 + tz * (c011 - c010)
    c10 = c100 + tz * (c101 - c100)
    c11 = c110 + tz * (c111 - c110)
    c0 = c00 + ty * (c01 - c00)
    c1 = c10 + ty * (c11 - c10)
    d = c0 + tx * (c1 - c0)
    gx = (c1 - c0) / h
    gy = ((1.0 - tx) * (c01 - c00) + tx * (c11 - c10)) / h
    dz0 = (1.0 - ty) * (c001 - c000) + ty * (c011 - c010)
    dz1 = (1.0 - ty) * (c101 - c100) + ty * (c111 - c110)
    gz = ((1.0 - tx) * dz0 + tx * dz1) / h
    return d, gx, gy, gz


@nb.njit(cache=True, inline="always")
def plane_contact(nx, ny, nz, c, px, py, pz, vx, vy, vz):
    """Position and velocity of a free vertex after its contact with the plane
    ``n . x >= c``: moved back onto it along ``n``, the velocity into it removed.
    Branch-free (selects), so that a loop over worlds around it vectorises."""
    d = min(nx * px + ny * py + nz * pz - c, 0.0)
    vn = min(nx * vx + ny * vy + nz * vz, 0.0) if d < 0.0 else 0.0
    return px - d * nx, py - d * ny, pz - d * nz, vx - vn * nx, vy - vn * ny, vz - vn * nz


@nb.njit(cache=True, inline="always")
def plane_axis(nx, ny, nz):
    """The axis (0, 1, 2) a unit plane normal lies along, or -1 if it is oblique."""
    if ny == 0.0 and nz == 0.0:
        return 0
    if nx == 0.0 and nz == 0.0:
        return 1
    if nx == 0.0 and ny == 0.0:
        return 2
    return -1


@nb.njit(cache=True, inline="always")
def axis_plane_contact(sign, c, p, v):
    """:func:`plane_contact` for a plane whose normal is ``sign`` (+1 or -1) times a
    coordinate axis, on that coordinate alone: ``(p, v)`` after the contact."""
    d = min(sign * p - c, 0.0)
    return p - d * sign, (sign * min(sign * v, 0.0) * -1.0 + v) if d < 0.0 else v


@nb.njit(cache=True, inline="always")
def project_out_of_supports(planes, grids, grid_values, px, py, pz, vx, vy, vz):
    """Position and velocity of a free vertex after its contacts with the supports.

    Inside a plane's half-space boundary (``n . p < c``) the vertex moves back onto the
    plane along ``n`` and its velocity loses any component into it; likewise inside a
    grid's surface (``d < 0``) along the normalised distance gradient.
    """
    for k in range(planes.shape[0]):
        nx = planes[k, 0]
        ny = planes[k, 1]
        nz = planes[k, 2]
        d = nx * px + ny * py + nz * pz - planes[k, 3]
        if d < 0.0:  # as plane_contact, with a branch: most vertices are not in contact
            px -= d * nx
            py -= d * ny
            pz -= d * nz
            vn = nx * vx + ny * vy + nz * vz
            if vn < 0.0:
                vx -= vn * nx
                vy -= vn * ny
                vz -= vn * nz
    for g in range(grids.shape[0]):
        d, gx, gy, gz = grid_signed_distance(grids, grid_values, g, px, py, pz)
        norm = math.sqrt(gx * gx + gy * gy + gz * gz)
        if d < 0.0 and norm > 0.0:
            gx /= norm
            gy /= norm
            gz /= norm
            px -= d * gx
            py -= d * gy
            pz -= d * gz
            vn = min(gx * vx + gy * vy + gz * vz, 0.0)
            vx -= vn * gx
            vy -= vn * gy
            vz -= vn * gz
    return px, py, pz, vx, vy, vz


@nb.njit(cache=True, inline="always")
def project_free_vertices(x, v, fixed, kinematic, planes, grids, grid_values):
    """:func:`project_out_of_supports` for every vertex of ``x, v`` ``(n, 3)`` (m, m/s),
    in place, except the ``fixed`` and ``kinematic`` ones (``(n,)`` masks). Plane by plane over the vertices
    (the plane's constants stay in registers; the loop vectorises), then grid by grid."""
    n = x.shape[0]
    for k in range(planes.shape[0]):
        nx = planes[k, 0]
        ny = planes[k, 1]
        nz = planes[k, 2]
        c = planes[k, 3]
        axis = plane_axis(nx, ny, nz)
        if axis >= 0:  # one coordinate to look at
            sign = planes[k, axis]
            for i in range(n):
                p, w = axis_plane_contact(sign, c, x[i, axis], v[i, axis])
                free = not (fixed[i] or kinematic[i])
                x[i, axis] = p if free else x[i, axis]
                v[i, axis] = w if free else v[i, axis]
            continue
        for i in range(n):
            px, py, pz, vx, vy, vz = plane_contact(nx, ny, nz, c, x[i, 0], x[i, 1], x[i, 2], v[i, 0], v[i, 1], v[i, 2])
            free = not (fixed[i] or kinematic[i])
            x[i, 0] = px if free else x[i, 0]
            x[i, 1] = py if free else x[i, 1]
            x[i, 2] = pz if free else x[i, 2]
            v[i, 0] = vx if free else v[i, 0]
            v[i, 1] = vy if free else v[i, 1]
            v[i, 2] = vz if free else v[i, 2]
    if grids.shape[0]:
        for i in range(n):
            if not (fixed[i] or kinematic[i]):
                x[i, 0], x[i, 1], x[i, 2], v[i, 0], v[i, 1], v[i, 2] = project_out_of_supports(
                    planes[:0], grids, grid_values, x[i, 0], x[i, 1], x[i, 2], v[i, 0], v[i, 1], v[i, 2])


@nb.njit(cache=True)
def signed_distances(points, planes, grids, grid_values, distance, normal):
    """For each point (m) the smallest signed distance to any support (m; ``inf`` when
    there is none) and that support's unit outward normal, into ``distance (n,)`` and
    ``normal (n, 3)`` (zero deeper inside a grid than its band, where the sampled
    distance is flat)."""
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        best = math.inf
        bx = 0.0
        by = 0.0
        bz = 0.0
        for k in range(planes.shape[0]):
            d = planes[k, 0] * px + planes[k, 1] * py + planes[k, 2] * pz - planes[k, 3]
            if d < best:
                best = d
                bx = planes[k, 0]
                by = planes[k, 1]
                bz = planes[k, 2]
        for g in range(grids.shape[0]):
            d, gx, gy, gz = grid_signed_distance(grids, grid_values, g, px, py, pz)
            norm = math.sqrt(gx * gx + gy * gy + gz * gz)
            if d < best:  # deeper than the band the gradient vanishes: no normal there
                best = d
                inv = 1.0 / norm if norm > 0.0 else 0.0
                bx = gx * inv
                by = gy * inv
                bz = gz * inv
        distance[i] = best
        normal[i, 0] = bx
        normal[i, 1] = by
        normal[i, 2] = bz


# --------------------------------------------------------- building a distance grid
@nb.njit(cache=True)
def point_triangle_distance2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Squared distance (m^2) from p to the triangle abc (Ericson, *Real-Time Collision
    Detection*, 5.1.5: Voronoi regions of the vertices, edges and face; a degenerate
    triangle ends in one of its edges or vertices)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = bx, by, bz
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz = cx, cy, cz
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0 and d1 - d3 > 0.0:
            t = d1 / (d1 - d3)
            qx, qy, qz = ax + t * abx, ay + t * aby, az + t * abz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0 and d2 - d6 > 0.0:
            t = d2 / (d2 - d6)
            qx, qy, qz = ax + t * acx, ay + t * acy, az + t * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0 and (d4 - d3) + (d5 - d6) > 0.0:
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx, qy, qz = bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz)
        elif va + vb + vc != 0.0:
            denom = 1.0 / (va + vb + vc)
            v = vb * denom
            w = vc * denom
            qx, qy, qz = ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w
        else:  # degenerate (all three points on a line through p's projection): nearest vertex
            qx, qy, qz = ax, ay, az
            for ux, uy, uz in ((bx, by, bz), (cx, cy, cz)):
                if (px - ux) ** 2 + (py - uy) ** 2 + (pz - uz) ** 2 < (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2:
                    qx, qy, qz = ux, uy, uz
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


@nb.njit(cache=True)
def band_distances(vertices, faces, origin, h, dims, band, out):
    """Unsigned distance (m) from the grid nodes within ``band`` m of the triangles to the
    nearest triangle, into ``out (nx, ny, nz)`` (pre-filled with ``band``)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for f in range(faces.shape[0]):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        bx, by, bz = vertices[b, 0], vertices[b, 1], vertices[b, 2]
        cx, cy, cz = vertices[c, 0], vertices[c, 1], vertices[c, 2]
        lo_x = max(0, int(math.floor((min(ax, bx, cx) - band - origin[0]) / h)))
        hi_x = min(nx - 1, int(math.ceil((max(ax, bx, cx) + band - origin[0]) / h)))
        lo_y = max(0, int(math.floor((min(ay, by, cy) - band - origin[1]) / h)))
        hi_y = min(ny - 1, int(math.ceil((max(ay, by, cy) + band - origin[1]) / h)))
        lo_z = max(0, int(math.floor((min(az, bz, cz) - band - origin[2]) / h)))
        hi_z = min(nz - 1, int(math.ceil((max(az, bz, cz) + band - origin[2]) / h)))
        for i in range(lo_x, hi_x + 1):
            px = origin[0] + i * h
            for j in range(lo_y, hi_y + 1):
                py = origin[1] + j * h
                for k in range(lo_z, hi_z + 1):
                    pz = origin[2] + k * h
                    d2 = point_triangle_distance2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
                    if d2 < out[i, j, k] * out[i, j, k]:
                        out[i, j, k] = math.sqrt(d2)


@nb.njit(cache=True)
def _column_crossings(vertices, faces, origin, h, nx, ny, shift_x, shift_y, counts, starts, heights, fill):
    """Count (``fill`` False) or store (``fill`` True) the heights where the grid columns
    cross the triangles; see :func:`inside_by_parity`."""
    for f in range(faces.shape[0]):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        bx, by, bz = vertices[b, 0], vertices[b, 1], vertices[b, 2]
        cx, cy, cz = vertices[c, 0], vertices[c, 1], vertices[c, 2]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue  # vertical triangle: a column never crosses it
        lo_i = max(0, int(math.floor((min(ax, bx, cx) - shift_x - origin[0]) / h)))
        hi_i = min(nx - 1, int(math.ceil((max(ax, bx, cx) - shift_x - origin[0]) / h)))
        lo_j = max(0, int(math.floor((min(ay, by, cy) - shift_y - origin[1]) / h)))
        hi_j = min(ny - 1, int(math.ceil((max(ay, by, cy) - shift_y - origin[1]) / h)))
        for i in range(lo_i, hi_i + 1):
            px = origin[0] + i * h + shift_x
            for j in range(lo_j, hi_j + 1):
                py = origin[1] + j * h + shift_y
                # barycentric coordinates of the column in the triangle's xy projection
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / area
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / area
                w2 = 1.0 - w0 - w1
                if w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0:
                    if fill:
                        heights[starts[i, j] + counts[i, j]] = w0 * az + w1 * bz + w2 * cz
                    counts[i, j] += 1


@nb.njit(cache=True)
def inside_by_parity(vertices, faces, origin, h, dims, shift_x, shift_y, inside):
    """Mark the grid nodes inside a closed triangle surface, ``inside (nx, ny, nz)``.

    For each grid column (a vertical line through node ``(i, j)``, moved by ``shift_x,
    shift_y`` m so that it misses the triangles' edges and corners), the heights where it
    crosses the surface are collected; a node is inside when an odd number of crossings
    lie below it.
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    counts = np.zeros((nx, ny), dtype=np.int64)
    starts = np.zeros((nx, ny), dtype=np.int64)
    heights = np.empty(0)
    _column_crossings(vertices, faces, origin, h, nx, ny, shift_x, shift_y, counts, starts, heights, False)
    total = 0
    for i in range(nx):
        for j in range(ny):
            starts[i, j] = total
            total += counts[i, j]
            counts[i, j] = 0
    heights = np.empty(total)
    _column_crossings(vertices, faces, origin, h, nx, ny, shift_x, shift_y, counts, starts, heights, True)
    for i in range(nx):
        for j in range(ny):
            column = np.sort(heights[starts[i, j]:starts[i, j] + counts[i, j]])
            below = 0
            for k in range(nz):
                pz = origin[2] + k * h
                while below < column.shape[0] and column[below] < pz:
                    below += 1
                inside[i, j, k] = below % 2 == 1


# ------------------------------------------------------------------ rigid tools
#: tool shapes (:mod:`heml_gym.tools`): a capsule (radius, half-length along its local z)
#: and a box (half-extents along its local x, y, z)
CAPSULE = 0
BOX = 1


@nb.njit(cache=True, inline="always")
def tool_signed_distance(kind, size, pose, px, py, pz):
    """Signed distance (m, negative inside) of ``p`` to one posed tool and the unit outward
    normal there: ``kind`` (:data:`CAPSULE` or :data:`BOX`), ``size (3,)`` (capsule:
    radius, half-length; box: half-extents, m), ``pose (12,)`` (the tool's centre, m, then
    its rotation matrix row by row: its columns are the tool's axes in the world).
    Returns ``(d, nx, ny, nz)``."""
    dx = px - pose[0]
    dy = py - pose[1]
    dz = pz - pose[2]
    # local coordinates: R^T d
    lx = pose[3] * dx + pose[6] * dy + pose[9] * dz
    ly = pose[4] * dx + pose[7] * dy + pose[10] * dz
    lz = pose[5] * dx + pose[8] * dy + pose[11] * dz
    if kind == CAPSULE:
        cz = min(max(lz, -size[1]), size[1])
        ex = lx
        ey = ly
        ez = lz - cz
        r = math.sqrt(ex * ex + ey * ey + ez * ez)
        d = r - size[0]
        if r > 0.0:
            mx = ex / r
            my = ey / r
            mz = ez / r
        else:  # on the axis: any normal to it
            mx = 1.0
            my = 0.0
            mz = 0.0
    else:
        qx = abs(lx) - size[0]
        qy = abs(ly) - size[1]
        qz = abs(lz) - size[2]
        sx = 1.0 if lx >= 0.0 else -1.0
        sy = 1.0 if ly >= 0.0 else -1.0
        sz = 1.0 if lz >= 0.0 else -1.0
        if qx > 0.0 or qy > 0.0 or qz > 0.0:  # outside: to the nearest point of the box
            ox = max(qx, 0.0)
            oy = max(qy, 0.0)
            oz = max(qz, 0.0)
            d = math.sqrt(ox * ox + oy * oy + oz * oz)
            mx = sx * ox / d
            my = sy * oy / d
            mz = sz * oz / d
        else:  # inside: out through the nearest face
            mx = 0.0
            my = 0.0
            mz = 0.0
            if qx >= qy and qx >= qz:
                d = qx
                mx = sx
            elif qy >= qz:
                d = qy
                my = sy
            else:
                d = qz
                mz = sz
    # back to the world: R n
    nx = pose[3] * mx + pose[4] * my + pose[5] * mz
    ny = pose[6] * mx + pose[7] * my + pose[8] * mz
    nz = pose[9] * mx + pose[10] * my + pose[11] * mz
    return d, nx, ny, nz


@nb.njit(cache=True)
def tool_each(points, kind, size, pose, distance, normal):
    """Each posed tool's signed distance (m) of each point and its outward normal, into
    ``distance (T, k)`` and ``normal (T, k, 3)`` (``pose (T, 12)``: one world's)."""
    for t in range(kind.shape[0]):
        for i in range(points.shape[0]):
            d, nx, ny, nz = tool_signed_distance(kind[t], size[t], pose[t], points[i, 0], points[i, 1], points[i, 2])
            distance[t, i] = d
            normal[t, i, 0] = nx
            normal[t, i, 1] = ny
            normal[t, i, 2] = nz
