"""A fast CPU renderer for the SITL's scenes (pure: numpy + OpenCV, no pybullet).

The scenes are vertical prisms (boxes turned about the vertical, upright cylinders as ``CYLINDER_SIDES``-gon
prisms) inside a room, so every visible surface is a planar convex polygon. Per frame:

1. transform all vertices to the camera (optical frame: x right, y down, z forward), cull back faces and
   faces outside the frustum, clip the rest against the near plane (Sutherland-Hodgman);
2. draw face ids into an id buffer with ``cv2.fillConvexPoly`` in painter's order: the room's interior
   first (from inside a convex room its faces never overlap), then the bodies ordered by the side of the
   camera of a separating plane per pair (bodies do not interpenetrate; the faces of one convex body that
   face the camera never overlap);
3. per pixel (u, v), with the face's plane n.X = d in the camera frame, the inverse depth is linear in
   the pixel: 1/z = (n . K^-1 (u, v, 1)) / d, and so are the texture coordinates times 1/z (perspective-
   correct mapping). One 9-float row per face, gathered by id, gives depth and atlas coordinates;
4. colour: one bilinear ``cv2.remap`` from a texture atlas in which every face has its own copy of its
   texture, pre-multiplied by its (static) Lambert shading.

Depth is exact for the polygons (the z of the ray's hit along the optical axis); the pixel (u, v) is the
ray ((u - cx)/fx, (v - cy)/fy, 1), as for ``camera_sim``. Frames are NED throughout (no pybullet frame).
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from sim_sitl.scene import MATERIAL_CODE, Scene, SceneBody, TextureKey

log = logging.getLogger(__name__)

EDGE_ON_PX = 0.25    # a face whose plane passes nearer the camera than this many pixels' angle (at its nearest corner)
                     # is seen edge-on and not drawn
CYLINDER_SIDES = 32  # inscribed polygon: surface within r (1 - cos(pi/32)) = 0.5 % of r of the cylinder
LIGHT_TOWARD_NED = (0.3, -0.2, -1.0)  # direction to the light: pybullet's lightDirection (0.3, 0.2, 1) z-up
AMBIENT = 0.6  # pybullet tiny renderer's default light coefficients (ambient, diffuse)
DIFFUSE = 0.35
BACKGROUND_RGB = (255, 255, 255)
ATLAS_WIDTH_PX = 4096  # cv2.remap takes coordinates below 32768
# replicated border around each face's texture. A pixel on a face's edge may have its ray just miss the face
# (its centre within ~0.5 px outside): its lookup lands outside the face's texels by up to the pixel's
# footprint in texels (<= 13 texels over the test poses, more only at extreme grazing): the border catches it.
PAD_PX = 16
_SHIFT = 4  # sub-pixel bits for cv2.fillConvexPoly
# cv2.fillConvexPoly rounds vertices to whole pixels and fills boundaries inclusively (~0.5 px too much on
# every side); moving each edge 0.4 px inward makes coverage follow the pixel centres best: against pybullet
# ray casts through every pixel (office, 8 poses) 0.06 % of pixels off by > 1 cm instead of 0.23 %.
EDGE_INSET_PX = 0.4


@dataclass(frozen=True)
class _Face:
    vertices: NDArray[np.float64]  # (n, 3) NED, convex, in order
    normal: NDArray[np.float64]  # unit, toward the side it is seen from
    body: int  # index into the draw groups; -1 = room interior
    texture: TextureKey
    origin: NDArray[np.float64]  # texture frame: s = (X - origin).e_u / len_u in [0, 1] spans crop_u
    e_u: NDArray[np.float64]
    len_u_m: float
    e_v: NDArray[np.float64]
    len_v_m: float
    crop_u: tuple[float, float] = (0.0, 1.0)  # fraction of the texture's columns this face shows


def _prism_footprint(body: SceneBody) -> NDArray[np.float64]:
    """Footprint corners (n, 2) north-east, counter-clockwise seen from above (z up = -down)."""
    cn, ce = body.centre_ned_m[0], body.centre_ned_m[1]
    if body.kind == "box":
        hx, hy = body.size_m[0] / 2, body.size_m[1] / 2
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        c, s = math.cos(body.yaw_rad), math.sin(body.yaw_rad)
        R = np.array([[c, -s], [s, c]])  # yaw about down: north toward east
        return local @ R.T + [cn, ce]
    a = 2 * math.pi * np.arange(CYLINDER_SIDES) / CYLINDER_SIDES
    return np.stack([cn + body.radius_m * np.cos(a), ce + body.radius_m * np.sin(a)], axis=1)


def _body_faces(body: SceneBody, index: int) -> list[_Face]:
    """Outward faces of a vertical prism with the texture frame of each."""
    fp = _prism_footprint(body)
    n = len(fp)
    z_top = body.centre_ned_m[2] - body.height_m / 2  # NED: up is -z
    z_bot = body.centre_ned_m[2] + body.height_m / 2
    top = np.column_stack([fp, np.full(n, z_top)])
    bot = np.column_stack([fp, np.full(n, z_bot)])
    centre = np.asarray(body.centre_ned_m, dtype=float)
    key = body.texture_key
    down = np.array([0.0, 0.0, 1.0])
    faces = []
    for k in range(n):
        a, b = top[k], top[(k + 1) % n]
        edge = b - a
        length = float(np.linalg.norm(edge))
        e_u = edge / length
        normal = np.array([e_u[1], -e_u[0], 0.0])
        if normal @ (a - centre) < 0:
            normal = -normal
        crop = (k / n, (k + 1) / n) if body.kind == "cylinder" else (0.0, 1.0)
        faces.append(_Face(np.array([a, b, bot[(k + 1) % n], bot[k]]), normal, index, key, a, e_u, length,
                           down, body.height_m, crop))
    # caps: texture frame from the first two edges (a box's face) or the bounding square (a cylinder)
    if body.kind == "box":
        o = top[0]
        e1, e2 = top[1] - top[0], top[3] - top[0]
        l1, l2 = float(np.linalg.norm(e1)), float(np.linalg.norm(e2))
        e1, e2 = e1 / l1, e2 / l2
    else:
        o = np.array([centre[0] - body.radius_m, centre[1] - body.radius_m, z_top])
        e1, e2 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
        l1 = l2 = 2 * body.radius_m
    faces.append(_Face(top, -down, index, key, o, e1, l1, e2, l2))
    faces.append(_Face(bot[::-1], down, index, key, o + down * body.height_m, e1, l1, e2, l2))
    return faces


def _interior_faces(scene: Scene) -> list[_Face]:
    """The room's inner surfaces (one per slab), textured as the slab's face they are part of."""
    lo, hi = scene.interior_bounds_ned_m()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    centre = (lo + hi) / 2
    faces = []
    for i, body in enumerate(scene.bodies):
        if body.surface not in ("floor", "ceiling", "wall") or i >= _n_slabs(scene):
            continue
        for f in _body_faces(body, -1):
            if f.normal @ (centre - f.vertices[0]) <= 0:
                continue  # faces away from the room
            on_plane = np.abs((corners - f.vertices[0]) @ f.normal) < 1e-6
            if on_plane.sum() != 4:
                continue  # a side of the slab, not its inner face
            quad = corners[on_plane]
            mid = quad.mean(axis=0)
            ref = quad[0] - mid
            ang = [math.atan2(float(np.cross(ref, q - mid) @ f.normal), float(ref @ (q - mid))) for q in quad]
            faces.append(_Face(quad[np.argsort(ang)], f.normal, -1, f.texture, f.origin, f.e_u, f.len_u_m, f.e_v,
                               f.len_v_m, f.crop_u))
    return faces


def _n_slabs(scene: Scene) -> int:
    return 1 + int(scene.room.ceiling) + 4 * int(scene.room.walls)


def _pack(sizes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int]:
    """Shelf packing: top-left corners for (w, h) rectangles in an atlas ``width`` wide, and its height."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][1])
    pos: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf = 0
    for i in order:
        w, h = sizes[i]
        if x + w > width:
            x, y, shelf = 0, y + shelf, 0
        pos[i] = (x, y)
        x += w
        shelf = max(shelf, h)
    return pos, y + shelf


class RasterRenderer:
    """Renders one scene from any camera pose; construction builds the meshes and the texture atlas."""

    def __init__(self, scene: Scene, textures: dict[TextureKey, NDArray[np.uint8]],
                 inset_px: float = EDGE_INSET_PX) -> None:
        self.scene = scene
        self.inset_px = inset_px
        n_slabs = _n_slabs(scene)
        self.shell = scene.closed_room  # inside a closed room only the slabs' inner faces can be seen
        faces = _interior_faces(scene) if self.shell else []
        bodies = [b for i, b in enumerate(scene.bodies) if not (self.shell and i < n_slabs)]
        for j, b in enumerate(bodies):
            faces += _body_faces(b, j)
        self._warn_outside(bodies)
        self.faces = faces
        self.n_bodies = len(bodies)
        # per body: axis-aligned bounds for the far-to-near order
        self._body_lo = np.array([np.min(np.concatenate([f.vertices for f in faces if f.body == j]), axis=0)
                                  for j in range(self.n_bodies)]).reshape(-1, 3)
        self._body_hi = np.array([np.max(np.concatenate([f.vertices for f in faces if f.body == j]), axis=0)
                                  for j in range(self.n_bodies)]).reshape(-1, 3)
        # padded vertex table (faces have 4 or CYLINDER_SIDES vertices): repeat the last vertex
        max_n = max(len(f.vertices) for f in faces)
        self._verts = np.array([np.vstack([f.vertices, np.repeat(f.vertices[-1:], max_n - len(f.vertices), 0)])
                                for f in faces])  # (F, max_n, 3)
        self._n_verts = np.array([len(f.vertices) for f in faces])
        self._normal = np.array([f.normal for f in faces])
        self._plane_d = np.einsum("ij,ij->i", self._normal, self._verts[:, 0])
        self._face_body = np.array([f.body for f in faces])
        # per face: the material code of its body (the room's interior: matte); glass is never drawn: the camera
        # sees what is behind it, in colour and in depth (the physics still has the body)
        self._face_material = np.array([MATERIAL_CODE[bodies[f.body].material] if f.body >= 0 else 0 for f in faces],
                                       dtype=np.uint8)
        self._face_glass = self._face_material == MATERIAL_CODE["glass"]
        self._body_on_floor = np.array([b.surface == "floor" for b in bodies], dtype=bool)  # rugs: drawn first
        self._separate(bodies)
        self._build_atlas(textures)

    def _separate(self, bodies: list[SceneBody]) -> None:
        """A separating plane for every pair of bodies (they are static): n . x = c with body ``i`` on the side
        ``sign``. The body on the camera's side of it is the one that may hide the other (drawn later).

        Vertical prisms: a horizontal plane if their heights do not overlap, else a vertical one along the edge
        normal of either footprint with the widest gap (2-D separating axis theorem).
        """
        fps = [_prism_footprint(b) for b in bodies]
        zr = [(b.centre_ned_m[2] - b.height_m / 2, b.centre_ned_m[2] + b.height_m / 2) for b in bodies]
        rows: list[tuple[int, int, float, float, float, float, float]] = []
        for i in range(len(bodies)):
            for j in range(i + 1, len(bodies)):
                cand = [((0.0, 0.0, 1.0), zr[j][0] - zr[i][1], zr[i][1], zr[j][0]),
                        ((0.0, 0.0, 1.0), zr[i][0] - zr[j][1], zr[j][1], zr[i][0])]
                for fp in (fps[i], fps[j]):
                    e = np.roll(fp, -1, axis=0) - fp
                    for a in np.stack([e[:, 1], -e[:, 0]], axis=1) / np.hypot(e[:, 0], e[:, 1])[:, None]:
                        pi, pj = fps[i] @ a, fps[j] @ a
                        cand.append(((a[0], a[1], 0.0), pj.min() - pi.max(), pi.max(), pj.min()))
                        cand.append(((a[0], a[1], 0.0), pi.min() - pj.max(), pj.max(), pi.min()))
                best = max(range(len(cand)), key=lambda q: cand[q][1])
                n, gap, lo, hi = cand[best]
                if gap < -1e-6:
                    log.warning("raster: bodies %r and %r interpenetrate: their overlap may be drawn in the wrong "
                                "order", bodies[i].name, bodies[j].name)
                    continue
                sign_i = -1.0 if best % 2 == 0 else 1.0  # even candidates: body i on the low side
                rows.append((i, j, n[0], n[1], n[2], (lo + hi) / 2, sign_i))
        table = np.array(rows, dtype=float).reshape(-1, 7)
        self._pair_i = table[:, 0].astype(np.int64)
        self._pair_j = table[:, 1].astype(np.int64)
        self._pair_n = table[:, 2:5]
        self._pair_c = table[:, 5]
        self._pair_sign_i = table[:, 6]

    def _warn_outside(self, bodies: list[SceneBody]) -> None:
        if not self.shell:
            return
        lo, hi = self.scene.interior_bounds_ned_m()
        for j, b in enumerate(bodies):
            v = np.concatenate([f.vertices for f in _body_faces(b, j)])
            if np.any(v < lo - 1e-6) or np.any(v > hi + 1e-6):
                log.warning("raster: body %r reaches outside the room: its outside part is drawn over the walls",
                            b.name)

    def _build_atlas(self, textures: dict[TextureKey, NDArray[np.uint8]]) -> None:
        """Every face's texture crop, shaded, padded, packed; the affine maps world point -> atlas pixel."""
        light = np.asarray(LIGHT_TOWARD_NED) / np.linalg.norm(LIGHT_TOWARD_NED)
        tiles = []
        for f in self.faces:
            tex = textures[f.texture]
            c0, c1 = (round(f.crop_u[0] * tex.shape[1]), max(round(f.crop_u[1] * tex.shape[1]),
                                                                  round(f.crop_u[0] * tex.shape[1]) + 1))
            shade = AMBIENT + DIFFUSE * max(0.0, float(f.normal @ light))
            crop = np.clip(tex[:, c0:c1].astype(np.float32) * shade, 0, 255).astype(np.uint8)
            crop = cv2.copyMakeBorder(crop, PAD_PX, PAD_PX, PAD_PX, PAD_PX, cv2.BORDER_REPLICATE)
            tiles.append(cv2.cvtColor(crop, cv2.COLOR_RGB2RGBA))
        tiles.append(np.full((1 + 2 * PAD_PX, 1 + 2 * PAD_PX, 4), (*BACKGROUND_RGB, 255), np.uint8))
        pos, height = _pack([(t.shape[1], t.shape[0]) for t in tiles], ATLAS_WIDTH_PX)
        if height >= 32767:
            raise ValueError(f"raster: texture atlas too tall ({height} px): fewer or smaller textures")
        self.atlas = np.zeros((height, ATLAS_WIDTH_PX, 4), np.uint8)
        for t, (x, y) in zip(tiles, pos, strict=True):
            self.atlas[y:y + t.shape[0], x:x + t.shape[1]] = t
        # atlas_x = G_u . X + h_u, atlas_y = G_v . X + h_v for points X on the face (texel centres at +0.5)
        F = len(self.faces)
        self._G = np.zeros((F, 2, 3))
        self._h = np.zeros((F, 2))
        for i, (f, t, (x, y)) in enumerate(zip(self.faces, tiles[:F], pos[:F], strict=True)):
            w_in, h_in = t.shape[1] - 2 * PAD_PX, t.shape[0] - 2 * PAD_PX
            self._G[i, 0] = f.e_u * (w_in / f.len_u_m)
            self._G[i, 1] = f.e_v * (h_in / f.len_v_m)
            self._h[i, 0] = x + PAD_PX - 0.5 - self._G[i, 0] @ f.origin
            self._h[i, 1] = y + PAD_PX - 0.5 - self._G[i, 1] @ f.origin
        bx, by = pos[-1]
        self._background_xy = (bx + PAD_PX, by + PAD_PX)
        self._grids: dict[tuple[int, int], tuple[NDArray[np.float32], NDArray[np.float32]]] = {}

    def _grid(self, k: CameraIntrinsics) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        key = (k.width, k.height)
        if key not in self._grids:
            u = np.arange(k.width, dtype=np.float32)[None, :].repeat(k.height, 0).ravel()
            v = np.arange(k.height, dtype=np.float32)[:, None].repeat(k.width, 1).ravel()
            self._grids[key] = (u, v)
        return self._grids[key]

    # ------------------------------------------------------------------ per frame
    def draw_order(self, p_ned_m: NDArray[np.float64], bodies: NDArray[np.int64] | None = None) -> list[int]:
        """Painter's order of ``bodies`` (default all): a body that may hide another is drawn after it.

        Exact for bodies that do not interpenetrate (``_separate``) unless their "hides" relation has a cycle,
        which convex bodies can form in principle; then, and for ties, bodies go far to near (floor-type first,
        then the distance from the camera to each body's bounding box, then to its centre).
        """
        if bodies is None:
            bodies = np.arange(self.n_bodies)
        if len(bodies) == 0:
            return []
        closest = np.clip(p_ned_m, self._body_lo, self._body_hi)
        d_box = np.linalg.norm(closest - p_ned_m, axis=1)
        d_centre = np.linalg.norm((self._body_lo + self._body_hi) / 2 - p_ned_m, axis=1)
        rank = np.empty(self.n_bodies, dtype=np.int64)
        rank[np.lexsort((-d_centre, -d_box, ~self._body_on_floor))] = np.arange(self.n_bodies)
        member = np.zeros(self.n_bodies, dtype=bool)
        member[bodies] = True
        pairs = member[self._pair_i] & member[self._pair_j]
        side = (self._pair_n[pairs] @ p_ned_m - self._pair_c[pairs]) * self._pair_sign_i[pairs]
        i, j = self._pair_i[pairs], self._pair_j[pairs]
        first = np.where(side > 0, j, i)  # the camera on i's side: i may hide j, so j first
        then = np.where(side > 0, i, j)
        indegree = np.bincount(then, minlength=self.n_bodies)
        after: dict[int, list[int]] = {}
        for a, b in zip(first.tolist(), then.tolist(), strict=True):
            after.setdefault(a, []).append(b)
        ready = [(int(rank[b]), int(b)) for b in bodies if indegree[b] == 0]
        heapq.heapify(ready)
        pending = {int(b) for b in bodies}
        order: list[int] = []
        while pending:
            if not ready:  # a cycle: take the farthest remaining body
                b = min(pending, key=lambda q: rank[q])
                ready.append((int(rank[b]), b))
                indegree[b] = 0
            _, b = heapq.heappop(ready)
            if b not in pending:
                continue
            pending.discard(b)
            order.append(b)
            for c in after.get(b, ()):
                indegree[c] -= 1
                if indegree[c] == 0 and c in pending:
                    heapq.heappush(ready, (int(rank[c]), c))
        return order

    def render(self, p_ned_m: NDArray[np.float64], R_ned_c: NDArray[np.float64], k: CameraIntrinsics,
               near_m: float, far_m: float) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """Colour (H x W x 3 RGB8) and optical-axis depth (m, float32; ``far_m`` where nothing is hit) seen
        by a camera at ``p_ned_m`` with ``R_ned_c`` (optical -> NED) and intrinsics ``k``."""
        rgb, depth, _ = self._render(p_ned_m, R_ned_c, k, near_m, far_m, False)
        return rgb, depth

    def render_layers(self, p_ned_m: NDArray[np.float64], R_ned_c: NDArray[np.float64], k: CameraIntrinsics,
                      near_m: float, far_m: float) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.uint8]]:
        """As :meth:`render`, plus each pixel's material code (``scene.MATERIAL_CODE``; background: matte)."""
        rgb, depth, material = self._render(p_ned_m, R_ned_c, k, near_m, far_m, True)
        assert material is not None
        return rgb, depth, material

    def _render(self, p_ned_m: NDArray[np.float64], R_ned_c: NDArray[np.float64], k: CameraIntrinsics,
                near_m: float, far_m: float, with_material: bool
                ) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.uint8] | None]:
        p = np.asarray(p_ned_m, dtype=float)
        R = np.asarray(R_ned_c, dtype=float)
        W, H = k.width, k.height
        Xc = (self._verts - p) @ R  # (F, n, 3) camera frame
        front = self._plane_d - self._normal @ p < 0  # camera on the side the face looks at
        z = Xc[..., 2]
        x_lim = max(k.cx, W - 1 - k.cx) / k.fx * 1.05 + 0.01  # frustum half-width (tan), a little margin
        y_lim = max(k.cy, H - 1 - k.cy) / k.fy * 1.05 + 0.01
        outside = ((z < near_m).all(1) | (z > far_m).all(1) | (Xc[..., 0] > x_lim * z).all(1)
                   | (Xc[..., 0] < -x_lim * z).all(1) | (Xc[..., 1] > y_lim * z).all(1)
                   | (Xc[..., 1] < -y_lim * z).all(1))
        # a face whose plane passes (almost) through the camera is seen edge-on: it covers no pixel, but its
        # projected corners are thrown far apart and crossed, cv2 fills a band of the image with it, and the depth of
        # its plane at those pixels comes out near 0 (a column's side from 1.9 mm off its plane and 2.8 m away: a
        # 25-row band at 0.03-0.5 m, whose structured-light shadow hid the floor, which read as an object 0.7 m ahead
        # of the vehicle and stopped a demo's approach). Not drawn: its whole projection lies within EDGE_ON_PX of
        # the line its plane projects to.
        gap_m = -(self._plane_d - self._normal @ p)   # the camera's height in front of each face's plane
        corner_m = np.sqrt(np.einsum("fnk,fnk->fn", Xc, Xc)).min(axis=1)   # to the face's nearest corner
        edge_on = gap_m < corner_m * (EDGE_ON_PX / max(k.fx, k.fy))
        visible = front & ~outside & ~self._face_glass & ~edge_on
        order = [np.flatnonzero(visible & (self._face_body == -1))]
        in_view = np.unique(self._face_body[visible & (self._face_body >= 0)])
        for j in self.draw_order(p, in_view):
            order.append(np.flatnonzero(visible & (self._face_body == j)))
        drawn = np.concatenate(order)
        # ids: 0 = background, drawn[i] -> i + 1; 8 bits (cv2.LUT gathers) unless more faces are in view
        ids = np.zeros((H, W), np.uint8 if len(drawn) < 256 else np.int32)
        for slot, poly in enumerate(self._screen_polygons(Xc, drawn, k, near_m), start=1):
            if poly is not None:
                cv2.fillConvexPoly(ids, poly, slot, cv2.LINE_8, _SHIFT)
        coef = self._coefficients(p, R, k, far_m, drawn)  # (9, len(drawn) + 1)
        if ids.dtype == np.uint8:
            table = np.zeros((len(coef), 256), np.float32)
            table[:, :coef.shape[1]] = coef
            c = [cv2.LUT(ids, table[j]).ravel() for j in range(len(coef))]
        else:
            c = list(np.take(coef, ids.ravel(), axis=1))
        u, v = self._grid(k)
        inv_z = c[0] * u
        inv_z += c[1] * v
        inv_z += c[2]
        np.maximum(inv_z, np.float32(1.0 / far_m), out=inv_z)  # an edge pixel's ray may meet its plane behind
        depth = np.float32(1.0) / inv_z
        # a pixel on a face's edge whose ray misses the face meets its plane elsewhere: nearer or farther than any
        # point of the face, wildly so on a face seen nearly edge-on. The face's depth (linear over it) lies between
        # its corners' (the near-clipped ones at the near plane): a pixel it fills is kept within that
        z_corner = Xc[drawn, :, 2]
        lo = np.zeros(len(drawn) + 1, np.float32)
        hi = np.full(len(drawn) + 1, np.inf, np.float32)
        lo[1:] = np.maximum(z_corner.min(axis=1), near_m)
        hi[1:] = np.maximum(z_corner.max(axis=1), lo[1:])
        if ids.dtype == np.uint8:
            lut_lo, lut_hi = np.zeros(256, np.float32), np.full(256, np.inf, np.float32)
            lut_lo[:len(lo)], lut_hi[:len(hi)] = lo, hi
            np.clip(depth, cv2.LUT(ids, lut_lo).ravel(), cv2.LUT(ids, lut_hi).ravel(), out=depth)
        else:
            np.clip(depth, lo[ids.ravel()], hi[ids.ravel()], out=depth)
        ax = c[3] * u
        ax += c[4] * v
        ax += c[5]
        ax *= depth
        ay = c[6] * u
        ay += c[7] * v
        ay += c[8]
        ay *= depth
        map1, map2 = cv2.convertMaps(ax.reshape(H, W), ay.reshape(H, W), cv2.CV_16SC2)
        rgba = cv2.remap(self.atlas, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        rgb = np.asarray(cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB), dtype=np.uint8)
        material: NDArray[np.uint8] | None = None
        if with_material:
            codes = np.zeros(len(drawn) + 1, np.uint8)
            codes[1:] = self._face_material[drawn]
            if ids.dtype == np.uint8:
                lut = np.zeros(256, np.uint8)
                lut[:len(codes)] = codes
                material = np.asarray(cv2.LUT(ids, lut), dtype=np.uint8)
            else:
                material = codes[ids]
        return rgb, depth.reshape(H, W).astype(np.float32, copy=False), material

    def _screen_polygons(self, Xc: NDArray[np.float64], drawn: NDArray[np.int64], k: CameraIntrinsics,
                         near_m: float) -> list[NDArray[np.int32] | None]:
        """Pixel polygons (fixed point, ``_SHIFT`` bits) of the faces ``drawn``, clipped to the near plane and
        moved ``inset_px`` inward; None for a face with nothing left. Batched by vertex count (no clipping)."""
        out: list[NDArray[np.int32] | None] = [None] * len(drawn)
        n_verts = self._n_verts[drawn]
        clip = Xc[drawn, :, 2].min(axis=1) < near_m
        groups: dict[int, tuple[list[int], list[NDArray[np.float64]]]] = {}
        for n in np.unique(n_verts[~clip]):
            sel = np.flatnonzero(~clip & (n_verts == n))
            groups[int(n)] = (sel.tolist(), [Xc[drawn[sel], :n]])
        for s in np.flatnonzero(clip):
            pts = _clip_near(Xc[drawn[s], :n_verts[s]], near_m)
            if len(pts) >= 3:
                slots, arrays = groups.setdefault(len(pts), ([], []))
                slots.append(int(s))
                arrays.append(pts[None])
        for slots, arrays in groups.values():
            for slot, poly in zip(slots, self._to_pixels(np.concatenate(arrays), k), strict=True):
                out[slot] = poly
        return out

    def _to_pixels(self, P: NDArray[np.float64], k: CameraIntrinsics) -> list[NDArray[np.int32] | None]:
        """(G, n, 3) camera-frame polygons (z > 0) -> fixed-point pixel polygons (inset), or None."""
        uv = np.empty(P.shape[:2] + (2,))
        uv[..., 0] = k.fx * P[..., 0] / P[..., 2] + k.cx
        uv[..., 1] = k.fy * P[..., 1] / P[..., 2] + k.cy
        if self.inset_px > 0:
            uv = _inset(uv, self.inset_px)
        pix = np.rint(uv * float(1 << _SHIFT))
        ok = np.asarray(np.isfinite(pix).all(axis=(1, 2)), dtype=bool)
        pix[~ok] = 0
        pix32 = pix.astype(np.int32)
        return [pix32[g] if ok[g] else None for g in range(len(P))]

    def _coefficients(self, p: NDArray[np.float64], R: NDArray[np.float64], k: CameraIntrinsics,
                      far_m: float, faces: NDArray[np.int64]) -> NDArray[np.float32]:
        """Columns (background, then ``faces``) of rows A, S, T: 1/z = A.(u, v, 1), atlas x = z S.(u, v, 1),
        atlas y = z T.(u, v, 1).

        With r = K^-1 (u, v, 1) and the plane n.X = d (NED): z (R^T n).r = d - n.p, so
        A = (R^T n)^T K^-1 / (d - n.p); and atlas x = G.(p + R z r) + h = z [(R^T G)^T K^-1 + (G.p + h) A].(u, v, 1).
        """
        Kinv = np.array([[1 / k.fx, 0.0, -k.cx / k.fx], [0.0, 1 / k.fy, -k.cy / k.fy], [0.0, 0.0, 1.0]])
        n, d, G, h = self._normal[faces], self._plane_d[faces], self._G[faces], self._h[faces]
        out = np.zeros((len(faces) + 1, 9))
        dc = d - n @ p
        dc = np.where(np.abs(dc) < 1e-9, -1e-9, dc)  # only front faces (dc < 0) are drawn
        A = (n @ R @ Kinv) / dc[:, None]
        out[1:, 0:3] = A
        GR = G @ R @ Kinv  # (F, 2, 3)
        off = G @ p + h  # (F, 2)
        out[1:, 3:6] = GR[:, 0] + off[:, 0:1] * A
        out[1:, 6:9] = GR[:, 1] + off[:, 1:2] * A
        out[0] = (0.0, 0.0, 1.0 / far_m, 0.0, 0.0, self._background_xy[0] / far_m, 0.0, 0.0,
                  self._background_xy[1] / far_m)
        return np.ascontiguousarray(out.T, dtype=np.float32)


def _clip_near(pts: NDArray[np.float64], near_m: float) -> NDArray[np.float64]:
    """Sutherland-Hodgman: the part of the convex polygon ``pts`` (camera frame) with z >= near_m."""
    out = []
    n = len(pts)
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        a_in, b_in = a[2] >= near_m, b[2] >= near_m
        if a_in:
            out.append(a)
        if a_in != b_in:
            t = (near_m - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


EDGE_MIN_PX = 1e-6   # a shorter edge is a repeated vertex (_inset)


def _inset(uv: NDArray[np.float64], d_px: float) -> NDArray[np.float64]:
    """Convex polygons (G, n, 2) in pixels with every edge moved ``d_px`` inward.

    A polygon that vanishes (thinner than 2 d_px: it covers no pixel centre) comes back as NaN; one with a
    degenerate edge (repeated or collinear vertices) comes back unchanged. Past vanishing the moved edges cross
    outside each other and the signed area may keep its sign (a sliver's bow-tie: a column's side seen just past
    ``EDGE_ON_PX`` 4 m away had a corner thrown 490 px along it, and cv2 filled a wedge across the image; a small
    triangle comes back turned 180 degrees): an output with a corner outside any moved edge has vanished.
    """
    n = uv.shape[1]
    nxt, prv = np.r_[1:n, 0], np.r_[n - 1, 0:n - 1]
    x, y = uv[..., 0], uv[..., 1]
    area2 = np.sum(x * y[:, nxt] - x[:, nxt] * y, axis=1)  # (G,)
    e = uv[:, nxt] - uv
    length = np.hypot(e[..., 0], e[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        nrm = np.sign(area2)[:, None, None] * np.stack([-e[..., 1], e[..., 0]], axis=-1) / length[..., None]
        c = np.sum(nrm * uv, axis=-1) + d_px  # inward edge lines: nrm_i . x = c_i
        n_prev, c_prev = nrm[:, prv], c[:, prv]
        det = n_prev[..., 0] * nrm[..., 1] - n_prev[..., 1] * nrm[..., 0]
        out = np.stack([(c_prev * nrm[..., 1] - c * n_prev[..., 1]) / det,
                        (n_prev[..., 0] * c - nrm[..., 0] * c_prev) / det], axis=-1)
    # an edge under a micro-pixel is a repeated vertex too: its normal is rounding noise (a triangle with two corners
    # 2e-16 px apart, hypothesis: its "inset" threw a corner 2 px outside the face)
    degenerate = ~np.isfinite(out).all(axis=(1, 2)) | (np.abs(det) < 1e-6).any(axis=1) | \
        (length < EDGE_MIN_PX).any(axis=1)
    ox, oy = out[..., 0], out[..., 1]
    with np.errstate(invalid="ignore", over="ignore"):   # a degenerate polygon's corners are inf or NaN here
        new_area2 = np.sum(ox * oy[:, nxt] - ox[:, nxt] * oy, axis=1)
    # every corner of a polygon that is left lies on the inner side of every moved edge; past vanishing the
    # corners are where the moved edges cross outside each other (a bow-tie, or a triangle turned 180 degrees)
    with np.errstate(invalid="ignore"):
        inner = np.einsum("gjk,gik->gij", nrm, out) - c[:, None, :]   # corner i against moved edge j
        tol = 1e-6 * (1.0 + np.abs(out).max(axis=(1, 2)))
        crossed = (inner < -tol[:, None, None]).any(axis=(1, 2))
    vanished = ~degenerate & ((new_area2 * area2 <= 0) | crossed)
    out[degenerate] = uv[degenerate]
    out[vanished | (area2 == 0)] = np.nan
    return out
