"""The camera renderer's per-pixel work, fused into compiled loops (numba), and the env's per-object boxes.

NumPy did it in a few dozen whole-image passes with temporaries (about 1.7 ms of a 6 ms step at
200x66); one loop per pixel does the same work in a fraction of that. Every float operation is
the one NumPy did, in the same precision and order (float32 for pixels, float64 for the ground
rays), and numba does not contract or reorder them without ``fastmath``, so frames stay bit for bit
what they were. ``cache=True`` keeps the compiled code in ``__pycache__`` across processes.

Parameter vectors (built by ``sim.render``; indices named below):
  ``geo`` float64: eye xyz, forward xyz, right xy, down xyz, focal, principal point (cx, cy),
  ground-map origin xy, texels per metre, slab and road plane heights.
  ``grade`` float32: depth-buffer constants, gain rgb, fog distance, fog colour rgb (already
  times gain), lift rgb, headlight ambient and gain, glow.
  ``flags`` int64: fog, lift, headlights, emissive windows, bloom.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

# geo
G_EYE, G_FWD, G_RIGHT, G_DOWN, G_FOCAL, G_CX, G_CY, G_ORIGIN, G_TEXELS, G_SLAB, G_ROAD = 0, 3, 6, 8, 11, 12, 13, 14, 16, 17, 18
GEO_SIZE = 19
# grade
P_NEAR_FAR, P_FAR, P_FAR_MINUS_NEAR, P_GAIN, P_FOG, P_FOG_RGB, P_LIFT, P_HL_AMBIENT, P_HL_GAIN, P_GLOW = (
    0, 1, 2, 3, 6, 7, 10, 13, 14, 15)
GRADE_SIZE = 16
# flags
F_FOG, F_LIFT, F_HEADLIGHTS, F_WINDOWS, F_BLOOM = 0, 1, 2, 3, 4


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _texel(texels: np.ndarray, x: float, y: float, x0: float, y0: float, per_m: float) -> int:
    """``GroundMap.lookup`` for one point: nearest texel, index clamped onto the grass border."""
    h, w = texels.shape
    ix = np.int32((x - x0) * per_m)
    iy = np.int32((y - y0) * per_m)
    ix = min(max(ix, 0), w - 1)
    iy = min(max(iy, 0), h - 1)
    return texels[iy, ix]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def shade_frame(rgba: np.ndarray, buf: np.ndarray, seg: np.ndarray, class_lut: np.ndarray, id_lut: np.ndarray,
                emit_mask: np.ndarray, night_emit: np.ndarray, emissive: np.ndarray, palette: np.ndarray,
                surface_class: np.ndarray, surface_raised: np.ndarray, texels: np.ndarray, geo: np.ndarray,
                grade: np.ndarray, flags: np.ndarray, cone: np.ndarray, sky_img: np.ndarray, img: np.ndarray,
                depth: np.ndarray, semantic: np.ndarray, sky: np.ndarray, glow_src: np.ndarray, out: np.ndarray,
                seen: np.ndarray, box: np.ndarray) -> tuple[bool, int]:
    """TinyRenderer's buffers to a graded float image, metric depth, (class, id) and the sky mask.

    Per pixel: z-depth from the depth buffer; (class, id) from the (body, link) lookup tables;
    below the horizon, the ray to the slab plane (then the road plane where the slab surface is
    not raised) replaces the mesh where it is nearer; then fog, gain, lift and headlights; lit
    emissive pixels take their own colour. Without bloom (``flags[F_BLOOM]`` 0) the finished uint8
    pixel (sky painted, clipped) goes straight to ``out`` and ``img``, ``sky`` and ``glow_src`` are
    left alone; with bloom the graded pixel goes to ``img``, emissive ones also to ``glow_src`` (all
    other pixels there are set to 0), and ``finish_frame`` completes the frame after the blur.
    On the way it does ``_fill_boxes``' work on the object ids it writes (``seen``, ``box``; see there).
    Returns whether any pixel was emissive, and ``_fill_boxes``' count (-1: more ids than ``seen`` holds).
    """
    h, w = buf.shape
    sky_key = class_lut.shape[0] - 1
    near_far, far, far_minus_near = grade[P_NEAR_FAR], grade[P_FAR], grade[P_FAR_MINUS_NEAR]
    one, fifteen, c255 = np.float32(1.0), np.float32(15.0), np.float32(255.0)
    inf32 = np.float32(np.inf)
    fx, fy, fz = geo[G_FWD], geo[G_FWD + 1], geo[G_FWD + 2]
    rx, ry = geo[G_RIGHT], geo[G_RIGHT + 1]
    dx, dy, dz = geo[G_DOWN], geo[G_DOWN + 1], geo[G_DOWN + 2]
    ex, ey, ez = geo[G_EYE], geo[G_EYE + 1], geo[G_EYE + 2]
    focal, cx, cy = geo[G_FOCAL], geo[G_CX], geo[G_CY]
    ox, oy, per_m = geo[G_ORIGIN], geo[G_ORIGIN + 1], geo[G_TEXELS]
    fog_on, lift_on, headlights, windows = flags[F_FOG] != 0, flags[F_LIFT] != 0, flags[F_HEADLIGHTS] != 0, flags[F_WINDOWS] != 0
    bloom = flags[F_BLOOM] != 0
    # The first row whose ray points down (rays fall monotonically with the row).
    r0 = h
    for r in range(h):
        if fz + ((r - cy) / focal) * dz < -1e-4:
            r0 = r
            break
    any_emit = False
    col_t = np.empty(w)  # each column's (c - cx) / focal, the ray's slope across, computed once per column
    for c in range(w):
        col_t[c] = (c - cx) / focal
    n_ids, last_id, last = 0, 0, -1  # the object boxes, as in _fill_boxes
    for r in range(h):
        t = (r - cy) / focal
        dir_z = fz + t * dz
        z_hi_row = (geo[G_SLAB] - ez) / dir_z
        z_lo_row = (geo[G_ROAD] - ez) / dir_z
        for c in range(w):
            s = seg[r, c]
            d = near_far / (far - far_minus_near * buf[r, c])
            if s < 0:
                key = sky_key
                empty = True
            else:
                key = (s & 0xFFFFFF) * 9 + (s >> 24)
                empty = False
            cls = class_lut[key]
            oid = id_lut[key]
            v0, v1, v2 = np.float32(rgba[r, c, 0]), np.float32(rgba[r, c, 1]), np.float32(rgba[r, c, 2])
            if r >= r0 and z_hi_row < d:
                sc = col_t[c]
                ray_x = fx + t * dx + sc * rx
                ray_y = fy + t * dy + sc * ry
                surf = _texel(texels, ex + z_hi_row * ray_x, -(ey + z_hi_row * ray_y), ox, oy, per_m)
                if surface_raised[surf]:
                    g = np.float32(z_hi_row)
                else:
                    surf = _texel(texels, ex + z_lo_row * ray_x, -(ey + z_lo_row * ray_y), ox, oy, per_m)
                    g = np.float32(z_lo_row)
                if g > far:
                    g = inf32
                if g < d:
                    d = g
                    cls = surface_class[surf]
                    oid = 0
                    v0, v1, v2 = palette[surf, 0], palette[surf, 1], palette[surf, 2]
                    empty = False
            depth[r, c] = d
            semantic[r, c, 0] = cls
            semantic[r, c, 1] = oid
            if oid > 0 and n_ids >= 0:  # n_ids -1: too many, the caller falls back to object_boxes
                n_ids, last = _grow_box(seen, box, n_ids, last_id, last, oid, r, c)
                last_id = oid
            if empty and not bloom:
                out[r, c, 0], out[r, c, 1], out[r, c, 2] = _u8(sky_img[r, c, 0]), _u8(sky_img[r, c, 1]), _u8(sky_img[r, c, 2])
                continue  # the sky replaces whatever the grade would make of this pixel
            if fog_on:
                fog = d / (d + grade[P_FOG])
                keep = one - fog
                v0 = v0 * (keep * grade[P_GAIN]) + fog * grade[P_FOG_RGB]
                v1 = v1 * (keep * grade[P_GAIN + 1]) + fog * grade[P_FOG_RGB + 1]
                v2 = v2 * (keep * grade[P_GAIN + 2]) + fog * grade[P_FOG_RGB + 2]
            else:
                v0, v1, v2 = v0 * grade[P_GAIN], v1 * grade[P_GAIN + 1], v2 * grade[P_GAIN + 2]
            if lift_on:
                v0, v1, v2 = v0 + grade[P_LIFT], v1 + grade[P_LIFT + 1], v2 + grade[P_LIFT + 2]
            if headlights:
                q = d / fifteen
                illum = grade[P_HL_AMBIENT] + grade[P_HL_GAIN] * cone[r, c] / (one + q * q)
                v0, v1, v2 = v0 * illum, v1 * illum, v2 * illum
            lit = emit_mask[key] and (windows or not night_emit[key])
            if lit:
                any_emit = True
                v0, v1, v2 = emissive[key, 0] * c255, emissive[key, 1] * c255, emissive[key, 2] * c255
            if bloom:
                sky[r, c] = empty
                img[r, c, 0], img[r, c, 1], img[r, c, 2] = v0, v1, v2
                if lit:
                    glow_src[r, c, 0], glow_src[r, c, 1], glow_src[r, c, 2] = v0, v1, v2
                else:
                    glow_src[r, c, 0], glow_src[r, c, 1], glow_src[r, c, 2] = 0.0, 0.0, 0.0
            else:
                out[r, c, 0], out[r, c, 1], out[r, c, 2] = _u8(v0), _u8(v1), _u8(v2)
    return any_emit, n_ids


@nb.njit(cache=True, nogil=True, inline="always")
def _u8(v: np.float32) -> np.uint8:
    """np.clip(v, 0, 255).astype(np.uint8) for one float32."""
    if v < np.float32(0.0):
        return np.uint8(0)
    if v > np.float32(255.0):
        return np.uint8(255)
    return np.uint8(v)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def finish_frame(img: np.ndarray, sky: np.ndarray, sky_img: np.ndarray, glow: np.ndarray, glow_gain: np.ndarray,
                 out: np.ndarray) -> None:
    """After ``shade_frame`` with bloom: add ``glow_gain[0]`` times the blurred glow (skipped when 0), paint
    the sky, clip to uint8."""
    h, w = sky.shape
    g = glow_gain[0]
    zero = np.float32(0.0)
    for r in range(h):
        for c in range(w):
            for k in range(3):
                if sky[r, c]:
                    v = sky_img[r, c, k]
                elif g != zero:
                    v = img[r, c, k] + g * glow[r, c, k]
                else:
                    v = img[r, c, k]
                out[r, c, k] = _u8(v)


@nb.njit(cache=True, nogil=True, inline="always")
def _grow_box(seen: np.ndarray, box: np.ndarray, n: int, last_id: int, last: int, v: int, r: int,
              c: int) -> tuple[int, int]:
    """Add pixel (r, c) of object ``v`` to its box (rows are visited in order); returns the id count and
    ``v``'s slot, or (-1, -1) when ``v`` is new and ``seen`` is full. ``last_id``/``last``: the previous
    pixel's id and slot (neighbouring pixels mostly share one)."""
    if v != last_id:
        last = -1
        for k in range(n):
            if seen[k] == v:
                last = k
                break
        if last < 0:
            if n == len(seen):
                return -1, -1
            seen[n] = v
            box[n, 0], box[n, 1], box[n, 2], box[n, 3], box[n, 4] = c, r, c, r, 0
            last = n
            n += 1
    if c < box[last, 0]:
        box[last, 0] = c
    if c > box[last, 2]:
        box[last, 2] = c
    box[last, 3] = r  # rows only grow
    box[last, 4] += 1
    return n, last


@nb.njit(cache=True, nogil=True)
def _fill_boxes(ids: np.ndarray, seen: np.ndarray, box: np.ndarray) -> int:
    """``object_boxes``' pass: how many ids it found, or -1 when there were more than ``seen`` holds."""
    h, w = ids.shape
    n = 0
    last_id, last = 0, -1
    for r in range(h):
        for c in range(w):
            v = ids[r, c]
            if v <= 0:
                continue
            n, last = _grow_box(seen, box, n, last_id, last, v, r, c)
            if n < 0:
                return -1
            last_id = v
    return n


def object_boxes(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each object id > 0 in an id image, ascending, with its pixel box (x0, y0, x1, y1, inclusive) and pixel count.

    One compiled pass; a frame holds a few dozen ids at most and neighbouring pixels mostly share one,
    so a short linear search behind a last-id cache beats sorting every labelled pixel.
    """
    cap = 64
    while True:
        seen, box = np.empty(cap, np.int64), np.empty((cap, 5), np.int64)
        n = _fill_boxes(ids, seen, box)
        if n >= 0:
            break
        cap *= 4
    return sorted_boxes(seen, box, n)


def sorted_boxes(seen: np.ndarray, box: np.ndarray, n: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``object_boxes``' result from a filled ``seen`` and ``box`` with ``n`` ids (``_fill_boxes``, ``shade_frame``)."""
    rows = _sorted_box_rows(seen, box, n)
    return rows[0], rows[1], rows[2], rows[3], rows[4], rows[5]


@nb.njit(cache=True, nogil=True)
def _sorted_box_rows(seen: np.ndarray, box: np.ndarray, n: int) -> np.ndarray:
    """Rows: the first ``n`` ids of ``seen`` ascending (they are distinct), then their ``box`` columns in that
    order. One compiled call; argsort and fancy indexing on a dozen numbers cost more in NumPy's call overhead."""
    order = np.argsort(seen[:n])
    rows = np.empty((6, n), np.int64)
    for i in range(n):
        j = order[i]
        rows[0, i] = seen[j]
        for c in range(5):
            rows[c + 1, i] = box[j, c]
    return rows


@nb.njit(cache=True, nogil=True)
def in_view_wedge(pos: np.ndarray, radius: np.ndarray, x: float, y: float, heading: float, half_fov: float,
                  range_m: float, margin: float) -> np.ndarray:
    """Which discs (centre ``pos[k]``, radius ``radius[k]``) may show in a camera's horizontal wedge: those
    within 3 m of the camera, and those within range no further off its axis than ``half_fov`` plus the
    disc's angular radius plus ``margin`` (radians).

    The formula of the NumPy code it replaced, element by element; libm's atan2 and asin may differ from
    NumPy's vectorised ones in the last bit, which can only matter for a disc exactly on the wedge's edge,
    ``margin`` outside the picture either way.
    """
    n = pos.shape[0]
    out = np.empty(n, np.bool_)
    for k in range(n):
        dx, dy = pos[k, 0] - x, pos[k, 1] - y
        r = radius[k]
        dist = math.hypot(dx, dy)
        ang = abs((math.atan2(dy, dx) - heading + math.pi) % (2 * math.pi) - math.pi)
        reach = half_fov + math.asin(min(max(r / max(dist, 1e-6), 0.0), 1.0)) + margin
        out[k] = (dist <= r + 3.0) or (dist <= range_m + r and ang <= reach)
    return out


@nb.njit(cache=True, nogil=True)
def merge_share(rgba: np.ndarray, buf: np.ndarray, seg: np.ndarray, rgba_b: np.ndarray, buf_b: np.ndarray,
                seg_b: np.ndarray) -> int:
    """Fold another process's TinyRenderer buffers (the same camera, a disjoint set of bodies) into these, in place,
    as if one call had drawn both sets of bodies; returns how many pixels came from the other buffers.

    TinyRenderer keeps a fragment when its depth is at least the z-buffer's, so a pixel shows the last fragment, in
    draw order, of those nearest the camera; bodies are drawn in the order of their unique ids. So per pixel the
    nearer of the two wins (smaller depth-buffer value), and at equal depth the body with the larger id (segmentation
    mask: body id in the low 24 bits, link + 1 above; -1 where nothing was drawn). Exact unless two fragments of
    bodies in different shares lie so close in depth that the depth buffer's float32 holds the same value for both
    and the earlier body's was the nearer (the tests and bench/README.md count how often)."""
    h, w = seg.shape
    taken = 0
    for i in range(h):
        for j in range(w):
            sb = seg_b[i, j]
            if sb < 0:
                continue
            sa = seg[i, j]
            if sa >= 0:
                da, db = buf[i, j], buf_b[i, j]
                if db > da or (db == da and (sb & 0xFFFFFF) < (sa & 0xFFFFFF)):
                    continue
            seg[i, j] = sb
            buf[i, j] = buf_b[i, j]
            for c in range(4):
                rgba[i, j, c] = rgba_b[i, j, c]
            taken += 1
    return taken


@nb.njit(cache=True, nogil=True)
def tile_costs(tris: np.ndarray, first: np.ndarray, shown: np.ndarray, pv: np.ndarray, eye: np.ndarray, width: int,
               height: int, near: float, per_triangle: float) -> np.ndarray:
    """An estimate of TinyRenderer's work for each shown static tile: ``per_triangle`` for each triangle (vertex
    shading) plus, for each triangle facing the eye, the pixels of its screen bounding box clamped to the image,
    which TinyRenderer's rasteriser visits one by one (the whole image when the triangle crosses the near plane).
    ``tris`` (n, 3, 3) world-frame triangles, tile k's are ``first[k]:first[k + 1]``; ``pv`` projection times view
    (row-major). Only balances the processes' shares (``SceneRenderer._balance``): the frame does not depend on it."""
    n_tiles = len(first) - 1
    cost = np.zeros(n_tiles)
    full = float(width * height)
    for k in range(n_tiles):
        if not shown[k]:
            continue
        c = per_triangle * (first[k + 1] - first[k])
        for t in range(first[k], first[k + 1]):
            ax, ay, az = tris[t, 1, 0] - tris[t, 0, 0], tris[t, 1, 1] - tris[t, 0, 1], tris[t, 1, 2] - tris[t, 0, 2]
            bx, by, bz = tris[t, 2, 0] - tris[t, 0, 0], tris[t, 2, 1] - tris[t, 0, 1], tris[t, 2, 2] - tris[t, 0, 2]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            if ((tris[t, 0, 0] - eye[0]) * nx + (tris[t, 0, 1] - eye[1]) * ny + (tris[t, 0, 2] - eye[2]) * nz) >= 0:
                continue  # back face: culled after the vertex shader
            x0, x1, y0, y1 = 1e30, -1e30, 1e30, -1e30
            behind = 0
            for v in range(3):
                x, y, z = tris[t, v, 0], tris[t, v, 1], tris[t, v, 2]
                cw = pv[3, 0] * x + pv[3, 1] * y + pv[3, 2] * z + pv[3, 3]
                if cw < near:
                    behind += 1
                    continue
                sx = (pv[0, 0] * x + pv[0, 1] * y + pv[0, 2] * z + pv[0, 3]) / cw
                sy = (pv[1, 0] * x + pv[1, 1] * y + pv[1, 2] * z + pv[1, 3]) / cw
                x0, x1, y0, y1 = min(x0, sx), max(x1, sx), min(y0, sy), max(y1, sy)
            if behind == 3:
                continue
            if behind:
                c += full
                continue
            px0, px1 = max((x0 + 1.0) * 0.5 * width, 0.0), min((x1 + 1.0) * 0.5 * width, width - 1.0)
            py0, py1 = max((y0 + 1.0) * 0.5 * height, 0.0), min((y1 + 1.0) * 0.5 * height, height - 1.0)
            if px1 >= px0 and py1 >= py0:
                c += (px1 - px0 + 1.0) * (py1 - py0 + 1.0)
        cost[k] = c
    return cost


@nb.njit(cache=True, nogil=True)
def share_out(cost: np.ndarray, shown: np.ndarray, owner: np.ndarray, count: int, base: np.ndarray) -> None:
    """Give each shown tile to a process, in place in ``owner``: the costliest first, each to the process with the
    least work so far (``base``: each process's work before the tiles). Tiles out of view keep their owner."""
    load = base.copy()
    order = np.argsort(-cost, kind="mergesort")
    for k in order:
        if not shown[k]:
            continue
        best = 0
        for r in range(1, count):
            if load[r] < load[best]:
                best = r
        owner[k] = best
        load[best] += cost[k]
