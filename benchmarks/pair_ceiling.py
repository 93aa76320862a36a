"""Pair kernel against the machine's ceiling: flops and bytes per pair, roofline fractions.

Counts the floating-point operations and the device-memory bytes per candidate pair of the
narrow-phase kernel (``kernels/narrowphase.py``, ``overlap_kernel``) for the pair sets of
``benchmarks/pair_kernel.py`` (imported: same shapes, depths, seed and half-separated mix), then
on CUDA measures the machine's ceilings (FP32/FP64 peak from SM count x lanes x 2 x max clock,
memory bandwidth from a large device-to-device copy), times the kernel for cubes at 1% depth and
reports the fractions reached; if ``ncu`` is on the PATH, one launch is profiled as well.

Flops are counted by a float64 mirror of the kernel's per-pair algorithm written here in numpy
(``Mirror``): the same early-outs (bounding spheres, slab along the line of centres, separating
face planes), culling, clipping order, fan sums and cone volumes. It is validated against
``polydem.overlap(..., precision="float64")`` on every sampled pair (V and S_A).

Counting rule (per operator as written in the kernel source and in Warp's native builtins it calls;
no common-subexpression elimination across statements, no constant folding):

Identical subexpressions within one statement count once, e.g. (r + rb) * (r + rb) = 1 add + 1 mul.

* ``add``: add or subtract (a negation is a sign flip folded into the operand: free);
* ``mul``: multiply; ``fma``: a multiply whose product feeds an add (nvcc contracts a*b+c, and
  Warp compiles without fast math): dot3 = 1 mul + 2 fma, cross = 3 mul + 3 fma,
  mat33*vec3 = 3 mul + 6 fma, quat_rotate = 12 mul + 12 fma, quat*quat = 4 mul + 12 fma,
  quat_to_matrix = 3 quat_rotate (columns of the unit vectors, as Warp writes it);
* ``div``, ``sqrt``: one each (on a GPU an IEEE division or square root is a short sequence of
  several instructions; they are few here);
* ``cmp``: comparisons, min, max (not flops; abs is a free operand modifier).

flops = add + mul + 2 fma + div + sqrt. Integer and address arithmetic is not counted.

Bytes per pair to or from device memory: the per-pair kernel arguments (two shape indices, two
transforms in; V and five vec3 out), from the dtypes of the arrays the launch uses. The shape
arrays are shared by all pairs (a few hundred bytes, cached in L1/L2) and reported separately,
with the mirror's count of shape-data loads per pair (cache traffic, not DRAM) and of accesses to
the per-thread buffers (polygon double buffer, B's plane list, face id lists) that live in local
memory on a GPU because they are indexed dynamically.

    python benchmarks/pair_ceiling.py --device cuda:0     # GPU: ceilings, timing, ncu if present
    python benchmarks/pair_ceiling.py --device cpu        # counts and the CPU timing only

Results: a table on stdout and JSON ``benchmarks/results/pair_ceiling_<device>.json``.
"""

import argparse
import collections
import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import pair_kernel as pk  # noqa: E402  (benchmarks/pair_kernel.py: pair generation and timing)
from _meta import run_meta  # noqa: E402
from polydem.kernels.narrowphase import COINCIDENT_TOL, COORDINATE_NOISE  # noqa: E402

import polydem  # noqa: E402
from polydem.shapeset import ShapeSet  # noqa: E402

RESULTS = os.path.join(HERE, "results")

# Composite operations in counted units (see the module docstring).
DOT = {"mul": 1, "fma": 2}
CROSS = {"mul": 3, "fma": 3}
MATVEC = {"mul": 3, "fma": 6}
QROT = {"mul": 12, "fma": 12}
QMUL = {"mul": 4, "fma": 12}
QMAT = {"mul": 36, "fma": 36}
KINDS = ("add", "mul", "fma", "div", "sqrt", "cmp")
PARALLEL_COS = 0.999  # the kernel's pre-filter of the coincident-face test

# FP32 and FP64 lanes per SM by compute capability (non-tensor pipes).
LANES = {(8, 0): (64, 32), (8, 6): (128, 2), (8, 7): (128, 2), (8, 9): (128, 2), (9, 0): (128, 64)}
KNOWN_MAX_CLOCK_MHZ = {"H100": 1980, "H200": 1980, "A100": 1410}


class Tally:
    """Operation counts of one pair: arithmetic by kind, plus words moved (scalars and ints)."""

    def __init__(self):
        self.n = dict.fromkeys(KINDS, 0)
        # words: shape-data loads (global, cached) and per-thread buffer traffic (local memory on a
        # GPU); "init" is the zero initialisation of the buffers (which the compiler may drop).
        self.words = collections.Counter()

    def __call__(self, *composites, times=1, **kinds):
        for comp in (*composites, kinds):
            for k, v in comp.items():
                self.n[k] += v * times

    def move(self, what, scalars=0, ints=0):
        self.words[what + "_s"] += scalars
        self.words[what + "_i"] += ints

    def flops(self):
        n = self.n
        return n["add"] + n["mul"] + 2 * n["fma"] + n["div"] + n["sqrt"]

    def summary(self, scalar_bytes):
        out = dict(self.n)
        out["flops"] = self.flops()
        for what in ("shape_ld", "local_ld", "local_st", "local_init"):
            out[what + "_bytes"] = scalar_bytes * self.words[what + "_s"] + 4 * self.words[what + "_i"]
        return out


def qrot(q, v):
    """Warp's quat_rotate (q = x, y, z, w)."""
    c = 2.0 * q[3] * q[3] - 1.0
    d = 2.0 * float(q[:3] @ v)
    return v * c + q[:3] * d + np.cross(q[:3], v) * q[3] * 2.0


def qmul(a, b):
    xyz = a[3] * b[:3] + b[3] * a[:3] + np.cross(a[:3], b[:3])
    return np.array([*xyz, a[3] * b[3] - float(a[:3] @ b[:3])])


def qmat(q):
    return np.column_stack([qrot(q, e) for e in np.eye(3)])


class Mirror:
    """The kernel's per-pair algorithm in float64 numpy, every operation tallied.

    Reads the packed arrays of a float64 :class:`ShapeSet` (with its padded culling spheres), so
    that its decisions are the kernel's. Method and variable names follow the kernel's."""

    def __init__(self, shapes, scalar):
        self.vert_start = shapes.shape_vert_start.numpy()
        self.face_start = shapes.shape_face_start.numpy()
        self.radius = shapes.shape_radius.numpy().astype(np.float64)
        self.face_plane = shapes.face_plane.numpy().astype(np.float64)
        self.face_sphere = shapes.face_sphere.numpy().astype(np.float64)
        self.loop_start = shapes.face_loop_start.numpy()
        self.loop = shapes.face_loop.numpy()
        self.vert = shapes.vert.numpy().astype(np.float64)
        self.max_poly = shapes.default_poly_capacity
        self.max_faces = shapes.max_faces
        self.tol_rel = COINCIDENT_TOL[scalar]
        self.noise_rel = COORDINATE_NOISE[scalar]

    # -- helpers as in the kernel --------------------------------------------------------------

    def coplanar_relation(self, c, fa, gb, rot, pos, tol):
        fp, vert = self.face_plane, self.vert
        pa = fp[fa]
        c.move("shape_ld", scalars=8)
        na = pa[:3]
        nb = rot @ fp[gb][:3]
        db = fp[gb][3] + float(nb @ pos)
        c(MATVEC, DOT, add=1)
        cc = float(na @ nb)
        c(DOT, cmp=1)
        if abs(cc) < PARALLEL_COS:
            return 0
        for k in range(self.loop_start[fa], self.loop_start[fa + 1]):
            c(DOT, add=1, cmp=1)
            c.move("shape_ld", scalars=3, ints=1)
            if abs(float(nb @ vert[self.loop[k]]) - db) > tol:
                return 0
        for k in range(self.loop_start[gb], self.loop_start[gb + 1]):
            c(MATVEC, DOT, add=4, cmp=1)
            c.move("shape_ld", scalars=3, ints=1)
            if abs(float(na @ (rot @ vert[self.loop[k]] + pos)) - pa[3]) > tol:
                return 0
        c(cmp=1)
        return 1 if cc > 0.0 else -1

    def clip_face(self, c, face, face_is_a, planes, plane_ids, num_planes, rot, pos, tol):
        mp = self.max_poly
        zero3 = np.zeros(3)
        poly = np.zeros((2 * mp, 3))  # one buffer per pair in the kernel: zero-filled once, below
        begin = self.loop_start[face]
        count = self.loop_start[face + 1] - begin
        sph = self.face_sphere[face]
        centre = sph[:3]
        nf = self.face_plane[face][:3]
        c.move("shape_ld", scalars=8, ints=2)
        if not face_is_a:
            centre = rot @ centre + pos
            nf = rot @ nf
            c(MATVEC, MATVEC, add=3)
        for k in range(count):
            v = self.vert[self.loop[begin + k]]
            c.move("shape_ld", scalars=3, ints=1)
            if not face_is_a:
                v = rot @ v + pos
                c(MATVEC, add=3)
            poly[k] = v
            c.move("local_st", scalars=3)
        weight = 1.0
        surface = 1
        cur = 0
        for j in range(num_planes):
            if face_is_a:
                pl = planes[j]
                c.move("local_ld", scalars=4)
            else:
                pl = self.face_plane[plane_ids[j]]
                c.move("local_ld", ints=1)
                c.move("shape_ld", scalars=4)
            n, d = pl[:3], pl[3]
            dist = float(n @ centre) - d
            c(DOT, add=1, cmp=1)
            if dist <= -sph[3]:
                continue
            c(cmp=1)
            if dist > sph[3]:
                return 0.0, zero3, 1, 0
            c(DOT, cmp=1)
            if abs(float(nf @ n)) >= PARALLEL_COS:
                c.move("local_ld", ints=1)
                if face_is_a:
                    rel = self.coplanar_relation(c, face, plane_ids[j], rot, pos, tol)
                else:
                    rel = self.coplanar_relation(c, plane_ids[j], face, rot, pos, tol)
                if rel == 1:
                    weight = 0.5
                    continue
                if rel == -1:
                    surface = 0
                    continue
            # Sutherland-Hodgman against n.x <= d
            out = mp - cur
            n_out = 0
            prev = poly[cur + count - 1].copy()
            c.move("local_ld", scalars=3)
            s_prev = float(n @ prev) - d
            c(DOT, add=1)
            for k in range(count):
                v = poly[cur + k].copy()
                c.move("local_ld", scalars=3)
                s = float(n @ v) - d
                c(DOT, add=1, cmp=2)
                if (s <= 0.0) != (s_prev <= 0.0):
                    if n_out >= mp:
                        return 0.0, zero3, 1, 1
                    t = s_prev / (s_prev - s)
                    poly[out + n_out] = prev + t * (v - prev)
                    c(add=4, div=1, fma=3)
                    c.move("local_st", scalars=3)
                    n_out += 1
                c(cmp=1)
                if s <= 0.0:
                    if n_out >= mp:
                        return 0.0, zero3, 1, 1
                    poly[out + n_out] = v
                    c.move("local_st", scalars=3)
                    n_out += 1
                prev = v
                s_prev = s
            if n_out < 3:
                return 0.0, zero3, 1, 0
            cur = out
            count = n_out
        # Fan triangulation
        p0 = poly[cur]
        c.move("local_ld", scalars=3)
        area = 0.0
        area_c = zero3
        for k in range(1, count - 1):
            p1 = poly[cur + k]
            p2 = poly[cur + k + 1]
            c.move("local_ld", scalars=6)
            a2 = float(np.cross(p1 - p0, p2 - p0) @ nf)
            area += a2
            area_c = area_c + a2 * (p0 + p1 + p2)
            c(CROSS, DOT, add=6 + 1 + 6, fma=3)
        area = weight * 0.5 * area
        area_c = (weight * 0.5 / 3.0) * area_c
        c(mul=2 + 1 + 3, div=1)
        return area, area_c, surface, 0

    @staticmethod
    def cone(c, area, area_c, plane, origin):
        h = plane[3] - float(plane[:3] @ origin)
        v = area * h / 3.0
        vc = (h / 3.0) * (0.25 * area * origin + 0.75 * area_c)
        c(DOT, add=1, mul=1 + 1 + 3 + 3, div=2, fma=3)
        return v, vc

    def pair_geometry_in_a(self, c, sa, sb, xa, xb):
        zero3 = np.zeros(3)
        nothing = (0.0, zero3, zero3, zero3, zero3, zero3, 0)
        fp, fs, vert = self.face_plane, self.face_sphere, self.vert
        ra, rb = self.radius[sa], self.radius[sb]
        c.move("shape_ld", scalars=2)
        qa = xa[3:]
        qa_inv = np.array([-qa[0], -qa[1], -qa[2], qa[3]])
        pos = qrot(qa_inv, xb[:3] - xa[:3])
        dist2 = float(pos @ pos)
        c(QROT, DOT, add=3 + 1, mul=1, cmp=1)
        if dist2 >= (ra + rb) * (ra + rb):
            return nothing, "bounding_spheres"
        rot = qmat(qmul(qa_inv, xb[3:]))
        rot_t = rot.T
        pos_b = -(rot_t @ pos)
        tol = self.tol_rel * min(ra, rb) + self.noise_rel * (ra + rb)
        c(QMUL, QMAT, MATVEC, add=1, mul=1, fma=1, cmp=1)
        fa0, fa1 = self.face_start[sa], self.face_start[sa + 1]
        fb0, fb1 = self.face_start[sb], self.face_start[sb + 1]
        c.move("shape_ld", ints=4)

        dist = np.sqrt(dist2)
        u = np.array([0.0, 0.0, 1.0])
        lo = -(ra + rb)
        hi = ra + rb
        c(sqrt=1, add=1, cmp=1)
        if dist > tol:
            u = pos / dist
            c(div=3)
            h_a = -(ra + rb)
            c.move("shape_ld", ints=4)
            for iv in range(self.vert_start[sa], self.vert_start[sa + 1]):
                h_a = max(h_a, float(u @ vert[iv]))
                c(DOT, cmp=1)
                c.move("shape_ld", scalars=3)
            u_b = rot_t @ u
            c(MATVEC)
            h_b = -(ra + rb)
            for iv in range(self.vert_start[sb], self.vert_start[sb + 1]):
                h_b = max(h_b, -float(u_b @ vert[iv]))
                c(DOT, cmp=1)
                c.move("shape_ld", scalars=3)
            lo = dist - h_b - tol
            hi = h_a + tol
            c(add=3, cmp=1)
            if lo > hi:
                return nothing, "slab"

        tau_a, tau_b = 1.0, 0.0
        ids_a = []
        c.move("local_init", ints=self.max_faces)
        for f in range(fa0, fa1):
            pl = fp[f]
            c.move("shape_ld", scalars=4)
            n = pl[:3]
            sigma = float(n @ pos)
            c(DOT, mul=1, cmp=1)
            if sigma * tau_a > pl[3]:
                tau_a = pl[3] / sigma
                c(div=1)
            s = sigma - pl[3]
            c(add=1, cmp=1)
            if s > rb:
                return nothing, "planes_a_spheres"
            c(cmp=1)
            if s > 0.0:
                nb = rot_t @ n
                db = pl[3] - float(n @ pos)
                c(MATVEC, DOT, add=1)
                sep = True
                for iv in range(self.vert_start[sb], self.vert_start[sb + 1]):
                    c(DOT, cmp=1)
                    c.move("shape_ld", scalars=3)
                    if float(nb @ vert[iv]) <= db:
                        sep = False
                        break
                if sep:
                    return nothing, "planes_a_exact"
            c(cmp=1)
            if s <= -rb:
                continue
            sph = fs[f]
            c.move("shape_ld", scalars=4)
            ctr = sph[:3]
            uc = float(u @ ctr)
            c(DOT, add=1, cmp=1)
            if uc + sph[3] < lo:
                continue
            c(add=1, cmp=1)
            if uc - sph[3] > hi:
                continue
            c(DOT, add=3 + 1, mul=1, cmp=1)
            if float((ctr - pos) @ (ctr - pos)) > (sph[3] + rb) * (sph[3] + rb):
                continue
            ids_a.append(f)
            c.move("local_st", ints=1)
        planes_b = []
        ids_b = []
        c.move("local_init", scalars=4 * self.max_faces, ints=self.max_faces)
        for g in range(fb0, fb1):
            pl = fp[g]
            c.move("shape_ld", scalars=4)
            n = pl[:3]
            sigma = float(n @ pos_b)
            c(DOT, add=1, mul=1, cmp=1)
            if sigma * (1.0 - tau_b) > pl[3]:
                tau_b = 1.0 - pl[3] / sigma
                c(div=1, add=1)
            s = sigma - pl[3]
            c(add=1, cmp=1)
            if s > ra:
                return nothing, "planes_b_spheres"
            na = rot @ n
            c(MATVEC, cmp=1)
            if s > 0.0:
                da = pl[3] + float(na @ pos)
                c(DOT, add=1)
                sep = True
                for iv in range(self.vert_start[sa], self.vert_start[sa + 1]):
                    c(DOT, cmp=1)
                    c.move("shape_ld", scalars=3)
                    if float(na @ vert[iv]) <= da:
                        sep = False
                        break
                if sep:
                    return nothing, "planes_b_exact"
            c(cmp=1)
            if s <= -ra:
                continue
            sph = fs[g]
            c.move("shape_ld", scalars=4)
            ctr = rot @ sph[:3] + pos
            uc = float(u @ ctr)
            c(MATVEC, DOT, add=3 + 1, cmp=1)
            if uc + sph[3] < lo:
                continue
            c(add=1, cmp=1)
            if uc - sph[3] > hi:
                continue
            c(DOT, add=1, mul=1, cmp=1)
            if float(ctr @ ctr) > (sph[3] + ra) * (sph[3] + ra):
                continue
            planes_b.append(np.array([*na, pl[3] + float(na @ pos)]))
            ids_b.append(g)
            c(DOT, add=1)
            c.move("local_st", scalars=4, ints=1)

        origin = pos * (0.5 * (tau_a + tau_b))
        c(add=1, mul=1 + 3, cmp=1)
        if tau_b > tau_a:
            # The line of centres misses the overlap: apex at the foot of B's centre on the active
            # plane of A that it lies farthest above (as in the kernel).
            s_top, foot = -(ra + rb), pos
            for f in ids_a:
                pl = fp[f]
                c.move("shape_ld", scalars=4)
                sj = float(pl[:3] @ pos) - pl[3]
                c(DOT, add=1, cmp=1)
                if sj > s_top:
                    s_top, foot = sj, pos - sj * pl[:3]
                    c(add=3, mul=3)
            origin = foot if s_top > 0.0 else pos
            c(cmp=1)
        vol, vol_c = 0.0, zero3
        s_a, m_a, s_b, m_b = zero3, zero3, zero3, zero3
        overflow = 0
        c.move("local_init", scalars=2 * self.max_poly * 3)  # the polygon buffer, once per pair
        for j in range(len(ids_a)):
            c.move("local_ld", ints=1)
            area, area_c, surface, of = self.clip_face(c, ids_a[j], True, planes_b, ids_b, len(ids_b), rot, pos, tol)
            overflow |= of
            pl = fp[ids_a[j]]
            c.move("local_ld", ints=1)
            c.move("shape_ld", scalars=4)
            dv, dv_c = self.cone(c, area, area_c, pl, origin)
            if surface != 0:
                s_a = s_a + area * pl[:3]
                m_a = m_a + np.cross(area_c, pl[:3])
                c(CROSS, fma=3, add=3)
            vol += dv
            vol_c = vol_c + dv_c
            c(add=4)
        for j in range(len(ids_b)):
            c.move("local_ld", ints=1)
            area, area_c, surface, of = self.clip_face(c, ids_b[j], False, planes_b, ids_a, len(ids_a), rot, pos, tol)
            overflow |= of
            pl = planes_b[j]
            c.move("local_ld", scalars=4)
            dv, dv_c = self.cone(c, area, area_c, pl, origin)
            if surface != 0:
                s_b = s_b + area * pl[:3]
                m_b = m_b + np.cross(area_c, pl[:3])
                c(CROSS, fma=3, add=3)
            vol += dv
            vol_c = vol_c + dv_c
            c(add=4)
        rot_a = qmat(qa)
        c(QMAT)
        c(MATVEC, times=5)
        return (vol, rot_a @ vol_c, rot_a @ s_a, rot_a @ m_a, rot_a @ s_b, rot_a @ m_b, overflow), "clipped"

    def pair(self, sa, sb, xa, xb):
        """(V, first moment, S_A, M_A, S_B, M_B, overflow), exit point, Tally."""
        c = Tally()
        c.move("shape_ld", scalars=2)
        c(cmp=1)
        if self.radius[sb] <= self.radius[sa]:
            res, exit_ = self.pair_geometry_in_a(c, sa, sb, xa, xb)
            return res, exit_, c
        (vol, vol_c, s_b, m_b, s_a, m_a, of), exit_ = self.pair_geometry_in_a(c, sb, sa, xb, xa)
        r = xb[:3] - xa[:3]
        c(add=3, fma=3)
        c(CROSS, add=3, times=2)
        return (vol, vol_c + vol * r, s_a, m_a + np.cross(r, s_a), s_b, m_b + np.cross(r, s_b), of), exit_, c


# ---------------------------------------------------------------------------------------------
# Counting


def stats(values):
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return None
    return {
        "n": len(v),
        "mean": float(v.mean()),
        "std": float(v.std()),
        "min": float(v.min()),
        "p10": float(np.percentile(v, 10)),
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "max": float(v.max()),
    }


def count_case(name, shape, depth, n, sample, device):
    """Mirror the kernel on `sample` pairs (half from each half) of pair_kernel.py's set for one case."""
    pa, pb = pk.make_pairs(shape, n, depth, np.random.default_rng(12345), device)
    half = n // 2
    k = min(sample // 2, half)
    rows = np.concatenate([np.arange(k), half + np.arange(k)])
    # Validation: the mirror in float64 (float64 tolerances) against the float64 kernel.
    mirror64 = Mirror(ShapeSet([shape], device="cpu", precision="float64"), wp.float64)
    ref = polydem.overlap(shape, pa[rows], shape, pb[rows], device=device, precision="float64")
    # Counting: the float32 kernel's decisions, so its tolerances and its rounded shape data and
    # poses (arithmetic still in float64); the branches are compared with the float32 kernel's.
    shapes32 = ShapeSet([shape], device=device, precision="float32")
    _, outs32 = pk.time_kernel(shapes32, pa[rows], pb[rows], 0)
    mirror = Mirror(ShapeSet([shape], device="cpu", precision="float32"), wp.float32)
    size = 2.0 * shape.radius
    per = []
    err = {"abs_v": 0.0, "abs_s": 0.0, "rel_v": 0.0, "rel_s": 0.0, "touch_mismatch_f64": 0, "touch_mismatch_f32": 0}
    for j, i in enumerate(rows):
        res64, _, _ = mirror64.pair(0, 0, pa[i], pb[i])
        v64, s64 = max(res64[0], 0.0), res64[2]
        err["abs_v"] = max(err["abs_v"], abs(v64 - ref.volume[j]) / size**3)
        err["abs_s"] = max(err["abs_s"], float(np.abs(s64 - ref.area_vector[j]).max()) / size**2)
        if ref.volume[j] > 0.0:
            err["rel_v"] = max(err["rel_v"], abs(v64 - ref.volume[j]) / ref.volume[j])
            err["rel_s"] = max(
                err["rel_s"], float(np.linalg.norm(s64 - ref.area_vector[j]) / np.linalg.norm(ref.area_vector[j]))
            )
        err["touch_mismatch_f64"] += int((v64 > 0.0) != (ref.volume[j] > 0.0))
        res, exit_, tally = mirror.pair(0, 0, pa[i].astype(np.float32), pb[i].astype(np.float32))
        err["touch_mismatch_f32"] += int((res[0] > 0.0) != (outs32[0][j] > 0.0))
        per.append({"half": "touching" if i < half else "separated", "touch": res[0] > 0.0, "exit": exit_, "t": tally})

    def group(sel):
        sel = list(sel)
        if not sel:
            return None
        out = {"pairs": len(sel), "flops": stats([p["t"].flops() for p in sel])}
        for kind in KINDS:
            out[kind] = float(np.mean([p["t"].n[kind] for p in sel]))
        for prec, sb in (("float32", 4), ("float64", 8)):
            sums = [p["t"].summary(sb) for p in sel]
            out[prec] = {
                key: float(np.mean([s[key] for s in sums]))
                for key in ("shape_ld_bytes", "local_ld_bytes", "local_st_bytes", "local_init_bytes")
            }
        out["exits"] = dict(collections.Counter(p["exit"] for p in sel))
        return out

    groups = {
        "mix": group(per),
        "touching_half": group(p for p in per if p["half"] == "touching"),
        "separated_half": group(p for p in per if p["half"] == "separated"),
        "overlapping": group(p for p in per if p["touch"]),
        "not_overlapping": group(p for p in per if not p["touch"]),
    }
    return {
        "shape": name,
        "faces": shape.num_faces,
        "vertices": shape.num_vertices,
        "depth": depth,
        "pairs_in_set": n,
        "pairs_counted": len(rows),
        "overlapping_in_touching_half": float(np.mean([p["touch"] for p in per if p["half"] == "touching"])),
        "validation": {
            "max_error_volume": err["abs_v"],
            "max_error_area_vector": err["abs_s"],
            "units": "size^3, size^2",
            "max_relative_error_volume": err["rel_v"],
            "max_relative_error_area_vector": err["rel_s"],
            "overlap_flag_mismatches_float64": err["touch_mismatch_f64"],
            "overlap_flag_mismatches_vs_float32_kernel": err["touch_mismatch_f32"],
            "against": "float64 mirror vs polydem.overlap(precision='float64'); counting mirror vs float32 kernel V>0",
        },
        "groups": groups,
    }, (pa, pb)


def io_bytes(shapes):
    """Bytes per pair the launch reads and writes in device memory, from the actual argument arrays."""
    scalar = shapes.scalar
    vec3 = wp.types.vector(3, scalar)
    tf = wp.types.transformation(scalar)
    dev = "cpu"  # only the dtypes matter
    inputs = {
        "pair_shape_a": wp.zeros(1, dtype=int, device=dev),
        "pair_shape_b": wp.zeros(1, dtype=int, device=dev),
        "pair_pose_a": wp.zeros(1, dtype=tf, device=dev),
        "pair_pose_b": wp.zeros(1, dtype=tf, device=dev),
    }
    outputs = {"pair_volume": wp.zeros(1, dtype=scalar, device=dev)}
    for k in ("pair_volume_moment", "pair_area_a", "pair_moment_a", "pair_area_b", "pair_moment_b"):
        outputs[k] = wp.zeros(1, dtype=vec3, device=dev)
    read = {k: a.strides[0] for k, a in inputs.items()}
    write = {k: a.strides[0] for k, a in outputs.items()}
    shape_arrays = dict(
        zip(
            (
                "shape_vert_start shape_face_start shape_radius face_plane face_sphere face_loop_start face_loop vert"
            ).split(),
            shapes.kernel_args(),
            strict=True,
        )
    )
    shape_bytes = {k: int(a.size * wp.types.type_size_in_bytes(a.dtype)) for k, a in shape_arrays.items()}
    return {
        "precision": shapes.precision,
        "read_per_pair": read,
        "write_per_pair": write,
        "bytes_per_pair": sum(read.values()) + sum(write.values()),
        "shape_data_bytes_total": sum(shape_bytes.values()),
        "shape_data_bytes": shape_bytes,
        "note": "the overflow flag is written (atomically) only on a polygon-buffer overflow; not counted",
    }


# ---------------------------------------------------------------------------------------------
# Ceilings (CUDA only)


def max_clock(dev):
    """Max SM clock [MHz] and where it came from."""
    smi = shutil.which("nvidia-smi")
    if smi:
        try:
            out = subprocess.run(
                [smi, "--query-gpu=clocks.max.sm,name", "--format=csv,noheader,nounits"],
                capture_output=True,
                text=True,
                timeout=30,
            ).stdout.strip()
            line = out.splitlines()[dev.ordinal if len(out.splitlines()) > dev.ordinal else 0]
            mhz = float(line.split(",")[0])
            return mhz, f"nvidia-smi clocks.max.sm ({line.strip()})"
        except Exception as e:  # fall back to the table
            err = repr(e)
    else:
        err = "nvidia-smi not found"
    for key, mhz in KNOWN_MAX_CLOCK_MHZ.items():
        if key in dev.name:
            return float(mhz), f"known value for {key} ({err})"
    return None, f"unknown ({err})"


def peaks(dev):
    arch = getattr(dev, "arch", None)
    sms = getattr(dev, "sm_count", None)
    cc = (arch // 10, arch % 10) if arch else None
    fp32_lanes, fp64_lanes = LANES.get(cc, (128, None))
    mhz, clock_source = max_clock(dev)
    out = {
        "arch": arch,
        "sm_count": sms,
        "fp32_lanes_per_sm": fp32_lanes,
        "fp64_lanes_per_sm": fp64_lanes,
        "lanes_source": "table by compute capability" if cc in LANES else "default 128 FP32 (unknown arch)",
        "max_sm_clock_mhz": mhz,
        "clock_source": clock_source,
    }
    if sms and mhz:
        out["fp32_flops"] = sms * fp32_lanes * 2 * mhz * 1e6
        out["fp32_instr_per_s"] = sms * fp32_lanes * mhz * 1e6
        out["fp64_flops"] = sms * fp64_lanes * 2 * mhz * 1e6 if fp64_lanes else None
    return out


def copy_bandwidth(dev, nbytes=1 << 29, repeats=10):
    """Bytes read + written per second of a large device-to-device wp.copy, median of `repeats`."""
    n = nbytes // 4
    src = wp.zeros(n, dtype=wp.float32, device=dev)
    dst = wp.empty(n, dtype=wp.float32, device=dev)
    wp.copy(dst, src)
    wp.synchronize_device(dev)
    times = []
    for _ in range(repeats):
        try:
            e0 = wp.Event(dev, enable_timing=True)
            e1 = wp.Event(dev, enable_timing=True)
            with wp.ScopedDevice(dev):
                wp.record_event(e0)
                wp.copy(dst, src)
                wp.record_event(e1)
            wp.synchronize_device(dev)
            times.append(wp.get_event_elapsed_time(e0, e1) / 1e3)
            how = "CUDA events"
        except Exception:
            t0 = time.perf_counter()
            wp.copy(dst, src)
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t0)
            how = "host clock"
    del src, dst
    t = float(np.median(times))
    return {"bytes_per_copy": 2 * nbytes, "seconds": t, "bytes_per_second": 2 * nbytes / t, "timing": how}


# ---------------------------------------------------------------------------------------------
# Nsight Compute (CUDA only, if installed)

NCU_METRICS = [
    "smsp__sass_thread_inst_executed_op_fadd_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_fmul_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_ffma_pred_on.sum",
    "dram__bytes_read.sum",
    "dram__bytes_write.sum",
    "l1tex__t_bytes_pipe_lsu_mem_local_op_ld.sum",
    "l1tex__t_bytes_pipe_lsu_mem_local_op_st.sum",
]
NCU_EXTRA = [
    "gpu__time_duration.sum",
    "launch__registers_per_thread",
    "sm__warps_active.avg.pct_of_peak_sustained_active",
    "smsp__inst_executed.sum",
    "lts__t_bytes_equiv_l1sectormiss_pipe_lsu_mem_local_op_ld.sum",
]


def ncu_child(path, device):
    """Child process under ncu: one launch of the float32 kernel on the saved poses."""
    data = np.load(path)
    shapes = ShapeSet([pk.shape_library()["cube"]], device=device, precision="float32")
    pk.time_kernel(shapes, data["pa"].astype(np.float64), data["pb"].astype(np.float64), 0)


def run_ncu(pa, pb, dev, timeout=300):
    ncu = shutil.which("ncu")
    if not ncu:
        return {"available": False, "reason": "ncu not on PATH"}
    tmp = tempfile.mkdtemp(prefix="pair_ceiling_")
    path = os.path.join(tmp, "poses.npz")
    np.savez(path, pa=pa.astype(np.float32), pb=pb.astype(np.float32))
    out = {"available": True, "ncu": ncu, "pairs": len(pa)}
    for metrics in (NCU_METRICS + NCU_EXTRA, NCU_METRICS):
        cmd = [ncu, "--csv", "--print-units", "base", "--kernel-name", "regex:overlap_kernel", "--launch-count", "1"]
        cmd += ["--metrics", ",".join(metrics), sys.executable, os.path.abspath(__file__)]
        cmd += ["--device", dev.alias, "--ncu-child", path]
        out["command"] = " ".join(cmd)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except Exception as e:
            out["error"] = repr(e)
            break
        text = proc.stdout + "\n" + proc.stderr
        values = parse_ncu_csv(proc.stdout)
        if values:
            out["metrics"] = values
            out.pop("error", None)
            break
        out["returncode"] = proc.returncode
        out["error"] = (
            "ERR_NVGPUCTRPERM (no permission for GPU performance counters)"
            if "ERR_NVGPUCTRPERM" in text
            else "no metrics parsed"
        )
        out["output_tail"] = text[-3000:]
        if "ERR_NVGPUCTRPERM" in text:
            break
    shutil.rmtree(tmp, ignore_errors=True)
    if "metrics" in out:
        m = out["metrics"]
        n = len(pa)
        per = {k: v / n for k, v in m.items() if not k.startswith(("launch__", "sm__warps", "gpu__time"))}
        out["per_pair"] = per
        get = per.get
        if all(get(k) is not None for k in NCU_METRICS[:3]):
            out["per_pair"]["fp32_fadd_fmul_ffma"] = sum(get(k) for k in NCU_METRICS[:3])
            out["per_pair"]["flops_fadd_fmul_2ffma"] = (
                get(NCU_METRICS[0]) + get(NCU_METRICS[1]) + 2 * get(NCU_METRICS[2])
            )
        if get("dram__bytes_read.sum") is not None and get("dram__bytes_write.sum") is not None:
            out["per_pair"]["dram_bytes"] = get("dram__bytes_read.sum") + get("dram__bytes_write.sum")
    return out


def parse_ncu_csv(text):
    """{metric: value} from ncu --csv output (rows: ..., "Metric Name", "Metric Unit", "Metric Value")."""
    lines = [line for line in text.splitlines() if line.startswith('"')]
    if not lines:
        return {}
    values = {}
    for row in csv.DictReader(io.StringIO("\n".join(lines))):
        name, value = row.get("Metric Name"), row.get("Metric Value")
        if not name or value is None:
            continue
        try:
            values[name] = float(re.sub(r"[,\s]", "", value))
        except ValueError:
            continue
    return values


# ---------------------------------------------------------------------------------------------


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument(
        "--pairs", type=int, default=None, help="pairs per set (default as pair_kernel.py: 2^20 GPU, 4096 CPU)"
    )
    ap.add_argument("--sample", type=int, default=256, help="pairs per case run through the counting mirror")
    ap.add_argument("--cases", default="cube:0.001,cube:0.01,cube:0.1,rock20:0.01", help="shape:depth, counted")
    ap.add_argument("--repeats", type=int, default=None, help="timed launches (default 20 GPU, 5 CPU)")
    ap.add_argument("--ncu-pairs", type=int, default=1 << 20, help="pairs in the profiled launch")
    ap.add_argument("--no-ncu", action="store_true")
    ap.add_argument("--ncu-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/pair_ceiling_<device>.json)")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    dev = wp.get_device(args.device)
    if args.ncu_child:
        ncu_child(args.ncu_child, dev)
        return
    n = args.pairs or (1 << 20 if dev.is_cuda else 4096)
    repeats = args.repeats or (20 if dev.is_cuda else 5)
    out = args.out or os.path.join(RESULTS, f"pair_ceiling_{dev.alias.replace(':', '')}.json")
    record = {
        "meta": run_meta(dev),
        "config": {k: v for k, v in vars(args).items() if k not in ("out", "ncu_child")},
    }
    record["config"]["pairs"] = n
    record["counting_rule"] = (
        "per operator as written in the kernel and Warp's builtins; add=add/sub, mul, fma=contracted a*b+c, "
        "div, sqrt, cmp=compare/min/max (not flops); flops = add + mul + 2 fma + div + sqrt; negation free; "
        "no CSE across statements, no constant folding (quat_to_matrix = 3 quat_rotate)"
    )
    t_start = time.perf_counter()

    def save():
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        tmp = out + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(record, fh, indent=1)
        os.replace(tmp, out)

    lib = pk.shape_library()
    print(f"pair kernel against the ceiling on {dev.name} ({dev.alias}), Warp {wp.config.version}")
    print(f"\nflops per pair (mirror of the kernel, {args.sample} pairs per case; FMA = 2 flops)")
    print(
        f"{'shape':<8}{'depth':>7}{'mix':>8}{'touch½':>8}{'sd':>7}{'sep½':>7}{'sd':>6}{'cmp':>6}"
        f"{'loc ld':>7}{'loc st':>7}{'init':>6}{'shp ld':>7}{'rel V':>9}{'rel S':>9}{'flag':>5}"
    )
    counts = []
    cube_1pct = None
    for case in args.cases.split(","):
        name, depth = case.split(":")
        depth = float(depth)
        res, poses = count_case(name, lib[name], depth, n, args.sample, dev)
        counts.append(res)
        if name == "cube" and depth == 0.01:
            cube_1pct = poses
        g = res["groups"]
        t, s = g["touching_half"], g["separated_half"]
        b, val = g["mix"]["float32"], res["validation"]
        print(
            f"{name:<8}{depth:>7.3g}{g['mix']['flops']['mean']:>8.0f}{t['flops']['mean']:>8.0f}"
            f"{t['flops']['std']:>7.0f}{s['flops']['mean']:>7.0f}{s['flops']['std']:>6.0f}{g['mix']['cmp']:>6.0f}"
            f"{b['local_ld_bytes']:>7.0f}{b['local_st_bytes']:>7.0f}{b['local_init_bytes']:>6.0f}"
            f"{b['shape_ld_bytes']:>7.0f}{val['max_relative_error_volume']:>9.1e}"
            f"{val['max_relative_error_area_vector']:>9.1e}{val['overlap_flag_mismatches_vs_float32_kernel']:>5}",
            flush=True,
        )
        record["counts"] = counts
        save()
    print(
        "(mix: the benchmark's mix, half pushed in, half separated; sd: standard deviation; cmp: compares per pair;\n"
        " loc ld/st/init: float32 bytes per pair of the per-thread buffers, loaded/stored/zero-initialised; shp ld:\n"
        " shape-data bytes loaded (cached); rel V/S: float64 mirror vs polydem.overlap float64, largest relative\n"
        " error over overlapping pairs; flag: pairs whose V>0 differs between the counting mirror and the float32\n"
        " kernel)"
    )

    shapes32 = ShapeSet([lib["cube"]], device=dev, precision="float32")
    shapes64 = ShapeSet([lib["cube"]], device=dev, precision="float64")
    record["bytes"] = {"float32": io_bytes(shapes32), "float64": io_bytes(shapes64)}
    b32 = record["bytes"]["float32"]["bytes_per_pair"]
    print(
        f"\nbytes per pair in device memory: float32 {b32}, float64 {record['bytes']['float64']['bytes_per_pair']}"
        f" (shape data, shared: {record['bytes']['float32']['shape_data_bytes_total']} B for one cube, float32)"
    )
    save()

    if cube_1pct is None:
        cube_1pct = pk.make_pairs(lib["cube"], n, 0.01, np.random.default_rng(12345), dev)
    cube_counts = next((c for c in counts if c["shape"] == "cube" and c["depth"] == 0.01), None)
    pa, pb = cube_1pct
    t, _ = pk.time_kernel(shapes32, pa, pb, repeats)
    pairs_s = n / t
    timing = {"shape": "cube", "depth": 0.01, "precision": "float32", "pairs": n, "repeats": repeats}
    timing.update({"seconds": t, "pairs_per_second": pairs_s})
    if cube_counts:
        mix = cube_counts["groups"]["mix"]
        fpp = mix["flops"]["mean"]
        timing["flops_per_pair"] = fpp
        timing["flops_per_second"] = fpp * pairs_s
        timing["bytes_per_pair"] = b32
        timing["bytes_per_second"] = b32 * pairs_s
        timing["arithmetic_intensity"] = fpp / b32
    record["timing"] = timing
    print(f"\ncube 1% float32: {pairs_s / 1e6:.1f} Mpairs/s ({t / n * 1e9:.2f} ns/pair, median of {repeats})", end="")
    if cube_counts:
        print(f", {timing['flops_per_second'] / 1e9:.2f} GFLOP/s, {timing['bytes_per_second'] / 1e9:.2f} GB/s", end="")
    print()

    roof = {}
    if not dev.is_cuda:
        reason = "CPU device: no GPU ceilings (run with --device cuda:0)"
        roof = {"peaks": None, "bandwidth": None, "reason": reason}
        record["ncu"] = {"available": False, "reason": reason}
        print(reason)
    else:
        roof["peaks"] = peaks(dev)
        try:
            roof["bandwidth"] = copy_bandwidth(dev)
        except Exception as e:
            roof["bandwidth"] = None
            roof["bandwidth_error"] = repr(e)
        pk_ = roof["peaks"]
        bw = (roof.get("bandwidth") or {}).get("bytes_per_second")
        if cube_counts and pk_.get("fp32_flops"):
            fpp = timing["flops_per_pair"]
            instr = mix["add"] + mix["mul"] + mix["fma"] + mix["div"] + mix["sqrt"] + mix["cmp"]
            roof["fp32_peak_fraction"] = timing["flops_per_second"] / pk_["fp32_flops"]
            roof["pairs_per_second_bound_fp32"] = pk_["fp32_flops"] / fpp
            roof["fp32_instructions_per_pair"] = instr
            roof["pairs_per_second_bound_fp32_issue"] = pk_["fp32_instr_per_s"] / instr
            roof["fp32_issue_fraction"] = pairs_s / roof["pairs_per_second_bound_fp32_issue"]
            if pk_.get("fp64_flops"):
                roof["pairs_per_second_bound_fp64"] = pk_["fp64_flops"] / fpp
        if bw:
            roof["bandwidth_fraction"] = timing["bytes_per_second"] / bw
            roof["pairs_per_second_bound_bandwidth"] = bw / b32
        if bw and pk_.get("fp32_flops") and cube_counts:
            roof["machine_balance_flops_per_byte"] = pk_["fp32_flops"] / bw
            ai = timing["arithmetic_intensity"]
            roof["verdict"] = (
                f"arithmetic intensity {ai:.1f} flop/B vs machine balance {roof['machine_balance_flops_per_byte']:.1f}:"
                f" {'compute' if ai > roof['machine_balance_flops_per_byte'] else 'memory'}-bound by the roofline;"
                f" reached {roof['fp32_peak_fraction']:.1%} of FP32 peak and {roof['bandwidth_fraction']:.1%} of"
                " bandwidth"
            )
        record["roofline"] = roof
        save()
        print(
            f"peaks: {pk_.get('sm_count')} SMs x {pk_['fp32_lanes_per_sm']} FP32 lanes x 2"
            f" x {pk_['max_sm_clock_mhz']} MHz"
            f" ({pk_['clock_source']}) = {(pk_.get('fp32_flops') or 0) / 1e12:.1f} TFLOP/s FP32,"
            f" {(pk_.get('fp64_flops') or 0) / 1e12:.1f} FP64; copy bandwidth {(bw or 0) / 1e12:.2f} TB/s"
        )
        for key, label in (
            ("fp32_peak_fraction", "fraction of FP32 peak"),
            ("fp32_issue_fraction", "fraction of FP32 instruction issue (add/mul/fma/cmp/div/sqrt = 1)"),
            ("bandwidth_fraction", "fraction of copy bandwidth"),
            ("pairs_per_second_bound_fp32", "pairs/s bound by FP32 peak"),
            ("pairs_per_second_bound_fp32_issue", "pairs/s bound by FP32 issue"),
            ("pairs_per_second_bound_bandwidth", "pairs/s bound by bandwidth"),
        ):
            if key in roof:
                v = roof[key]
                print(f"  {label:<68}{v:.3%}" if "fraction" in key else f"  {label:<68}{v:.3g}")
        if "verdict" in roof:
            print("  " + roof["verdict"])
        if args.no_ncu:
            record["ncu"] = {"available": False, "reason": "--no-ncu"}
        else:
            m = min(args.ncu_pairs, n)
            half = n // 2
            rows = np.concatenate([np.arange(m // 2), half + np.arange(m - m // 2)])
            record["ncu"] = run_ncu(pa[rows], pb[rows], dev)
            nc = record["ncu"]
            if cube_counts:  # the mirror's counts for the same mix, to set beside the measured ones
                nc["mirror_per_pair"] = {k: mix[k] for k in ("add", "mul", "fma", "div", "sqrt", "cmp")}
                nc["mirror_per_pair"]["local_bytes_ld_st_init"] = [
                    mix["float32"][k] for k in ("local_ld_bytes", "local_st_bytes", "local_init_bytes")
                ]
            if "per_pair" in nc:
                print("ncu, per pair: " + ", ".join(f"{k} {v:.4g}" for k, v in nc["per_pair"].items()))
            else:
                print(f"ncu: {nc.get('reason') or nc.get('error')}")
    record["roofline"] = roof
    record["meta"]["total_s"] = time.perf_counter() - t_start
    save()
    print(f"wrote {out} ({record['meta']['total_s']:.0f} s)")


if __name__ == "__main__":
    main()
