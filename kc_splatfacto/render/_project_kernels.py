"""numba kernels: EWA projection and SH colours of every (camera, Gaussian) pair in one pass, and their backward.

The formulas are those of the torch reference (``projection.fully_fused_projection``, ``sh.sh_to_rgb``; gsplat 1.5.3
``ProjectionEWA3DGSFused.cu`` / ``SphericalHarmonicsCUDA.cu``), written per pair in float64 whatever the input dtype
(outputs are stored in the caller's arrays, float32 for training). The backward is the hand-written chain rule of
exactly those formulas (the reference's autograd gradients, including its conventions: a zero quaternion gives the
identity and zero gradient, a zero SH direction the degree-0 term, the clamp ``max(colour, 0)`` passes the gradient
at 0).

Scalars that come from ``constants.py`` are kernel ARGUMENTS (the ``params`` and ``sh_c`` arrays), never globals:
numba freezes globals into its on-disk cache, keyed on this file only.

Parallel over Gaussians (``prange``), cameras inside: each Gaussian's gradient is written by one thread, so the
results do not depend on the thread count.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# --- ``params`` (float64) row: scalars of one projection call -------------------------------------------------------
P_WIDTH, P_HEIGHT, P_EPS2D, P_NEAR, P_FAR, P_RADIUS_CLIP = 0, 1, 2, 3, 4, 5
P_ALPHA_THRESHOLD, P_EXTENT_SIGMA, P_FOV_MARGIN, P_RADIUS_MAX, P_COLOR_OFFSET = 6, 7, 8, 9, 10
N_PARAMS = 11

# --- ``sh_c`` (float64): gsplat's SH constants in basis order -------------------------------------------------------
# C0, C1, C2 (xy, zz, const, xx_yy), C3 (m=3, m=2, m=1 z^2, m=1 const, m=0 z^3, m=0 z)
N_SH_CONSTS = 12

# --- ``bad`` bits: which input of a Gaussian holds NaN/inf (checked while the kernel reads it) ---------------------
BAD_MEANS, BAD_QUATS, BAD_SCALES, BAD_OPACITIES, BAD_COLORS = 1, 2, 4, 8, 16

# A quaternion's norm is clamped at this floor before dividing (torch.nn.functional.normalize's eps).
NORM_EPS = 1e-12


@njit(inline="always", cache=True)
def _quat_to_rotmat(w, x, y, z):
    """Rotation matrix of a UNIT quaternion (wxyz), row-major as 9 scalars."""
    return (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@njit(inline="always", cache=True)
def _sh_bases_all(x, y, z, sh_c):
    """All 16 basis functions at (x, y, z) as a tuple (unrolled: no per-basis branches in the pixel-free loops)."""
    fc1 = x * x - y * y
    fs1 = 2.0 * x * y
    tmp_c = -sh_c[8] * z * z + sh_c[9]
    return (sh_c[0], -sh_c[1] * y, sh_c[1] * z, -sh_c[1] * x,
            sh_c[5] * fs1, -sh_c[2] * z * y, sh_c[3] * z * z - sh_c[4], -sh_c[2] * z * x, sh_c[5] * fc1,
            -sh_c[6] * (x * fs1 + y * fc1), sh_c[7] * z * fs1, tmp_c * y, z * (sh_c[10] * z * z - sh_c[11]),
            tmp_c * x, sh_c[7] * z * fc1, -sh_c[6] * (x * fc1 - y * fs1))


@njit(inline="always", cache=True)
def _sh_dot(sh_dc, sh_rest, cs, n, ch, n_bases, b):
    """sum_k b[k] sh[cs, n, k, ch] over the first n_bases (1, 4, 9 or 16) coefficients, coefficient 0 read from
    ``sh_dc`` and k >= 1 from ``sh_rest[..., k - 1, ch]`` (Splatfacto keeps them apart: no concatenated copy)."""
    v = b[0] * sh_dc[cs, n, 0, ch]
    if n_bases > 1:
        v += b[1] * sh_rest[cs, n, 0, ch] + b[2] * sh_rest[cs, n, 1, ch] + b[3] * sh_rest[cs, n, 2, ch]
    if n_bases > 4:
        v += (b[4] * sh_rest[cs, n, 3, ch] + b[5] * sh_rest[cs, n, 4, ch] + b[6] * sh_rest[cs, n, 5, ch]
              + b[7] * sh_rest[cs, n, 6, ch] + b[8] * sh_rest[cs, n, 7, ch])
    if n_bases > 9:
        v += (b[9] * sh_rest[cs, n, 8, ch] + b[10] * sh_rest[cs, n, 9, ch] + b[11] * sh_rest[cs, n, 10, ch]
              + b[12] * sh_rest[cs, n, 11, ch] + b[13] * sh_rest[cs, n, 12, ch] + b[14] * sh_rest[cs, n, 13, ch]
              + b[15] * sh_rest[cs, n, 14, ch])
    return v


@njit(inline="always", cache=True)
def _sh_scatter(v_sh_dc, v_sh_rest, cs, n, ch, n_bases, b, v):
    """v_sh[cs, n, k, ch] += b[k] v for the first n_bases coefficients (k = 0 in ``v_sh_dc``, k >= 1 in
    ``v_sh_rest[..., k - 1, ch]``)."""
    v_sh_dc[cs, n, 0, ch] += b[0] * v
    if n_bases > 1:
        v_sh_rest[cs, n, 0, ch] += b[1] * v
        v_sh_rest[cs, n, 1, ch] += b[2] * v
        v_sh_rest[cs, n, 2, ch] += b[3] * v
    if n_bases > 4:
        v_sh_rest[cs, n, 3, ch] += b[4] * v
        v_sh_rest[cs, n, 4, ch] += b[5] * v
        v_sh_rest[cs, n, 5, ch] += b[6] * v
        v_sh_rest[cs, n, 6, ch] += b[7] * v
        v_sh_rest[cs, n, 7, ch] += b[8] * v
    if n_bases > 9:
        v_sh_rest[cs, n, 8, ch] += b[9] * v
        v_sh_rest[cs, n, 9, ch] += b[10] * v
        v_sh_rest[cs, n, 10, ch] += b[11] * v
        v_sh_rest[cs, n, 11, ch] += b[12] * v
        v_sh_rest[cs, n, 12, ch] += b[13] * v
        v_sh_rest[cs, n, 13, ch] += b[14] * v
        v_sh_rest[cs, n, 14, ch] += b[15] * v


@njit(inline="always", cache=True)
def _sh_dir_vjp(sh_rest, cs, n, n_bases, x, y, z, v_r, v_g, v_b, sh_c):
    """Gradient of sum_k,ch v_ch basis_k(x, y, z) sh[cs, n, k, ch] w.r.t. the (unnormalized) components x, y, z
    (coefficient 0 is constant in the direction: only ``sh_rest`` enters)."""

    def vb(k):
        return v_r * sh_rest[cs, n, k - 1, 0] + v_g * sh_rest[cs, n, k - 1, 1] + v_b * sh_rest[cs, n, k - 1, 2]

    v_x = 0.0
    v_y = 0.0
    v_z = 0.0
    if n_bases > 1:
        v_y -= sh_c[1] * vb(1)
        v_z += sh_c[1] * vb(2)
        v_x -= sh_c[1] * vb(3)
    if n_bases > 4:
        vb4, vb5, vb6, vb7, vb8 = vb(4), vb(5), vb(6), vb(7), vb(8)
        v_x += 2.0 * sh_c[5] * y * vb4 - sh_c[2] * z * vb7 + 2.0 * sh_c[5] * x * vb8
        v_y += 2.0 * sh_c[5] * x * vb4 - sh_c[2] * z * vb5 - 2.0 * sh_c[5] * y * vb8
        v_z += -sh_c[2] * y * vb5 + 2.0 * sh_c[3] * z * vb6 - sh_c[2] * x * vb7
    if n_bases > 9:
        fc1 = x * x - y * y
        fs1 = 2.0 * x * y
        tmp_c = -sh_c[8] * z * z + sh_c[9]
        vb9, vb10, vb11, vb12, vb13, vb14, vb15 = vb(9), vb(10), vb(11), vb(12), vb(13), vb(14), vb(15)
        v_x += (-3.0 * sh_c[6] * fs1 * vb9 + 2.0 * sh_c[7] * z * y * vb10 + tmp_c * vb13
                + 2.0 * sh_c[7] * z * x * vb14 - 3.0 * sh_c[6] * fc1 * vb15)
        v_y += (-3.0 * sh_c[6] * fc1 * vb9 + 2.0 * sh_c[7] * z * x * vb10 + tmp_c * vb11
                - 2.0 * sh_c[7] * z * y * vb14 + 3.0 * sh_c[6] * fs1 * vb15)
        v_z += (sh_c[7] * fs1 * vb10 - 2.0 * sh_c[8] * z * y * vb11 + (3.0 * sh_c[10] * z * z - sh_c[11]) * vb12
                - 2.0 * sh_c[8] * z * x * vb13 + sh_c[7] * fc1 * vb14)
    return v_x, v_y, v_z


@njit(inline="always", cache=True)
def _camera(viewmats, Ks, c, params):
    """Per-camera scalars: W (9, row-major), t (3), fx, fy, cx, cy and the Jacobian's clamp limits (4)."""
    fx = Ks[c, 0, 0]
    fy = Ks[c, 1, 1]
    cx = Ks[c, 0, 2]
    cy = Ks[c, 1, 2]
    width = params[P_WIDTH]
    height = params[P_HEIGHT]
    margin = params[P_FOV_MARGIN]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + margin * tan_x
    lim_x_neg = cx / fx + margin * tan_x
    lim_y_pos = (height - cy) / fy + margin * tan_y
    lim_y_neg = cy / fy + margin * tan_y
    return fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg


@njit(parallel=True, cache=True, fastmath=False)
def project_sh_fwd(means, quats, scales, opacities, sh_dc, sh_rest, viewmats, Ks, campos, params, sh_c, antialiased, sh_degree,
                   radii, means2d, depths, conics, compensations, opacities_c, colors, bad):
    """Forward of every (camera, Gaussian) pair.

    Inputs: means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N], SH coefficients as sh_dc [Cs,N,1,3] and
    sh_rest [Cs,N,K-1,3] (Cs = 1 or C; ignored when ``sh_degree < 0``), viewmats [C,4,4], Ks [C,3,3], campos [C,3] camera centres, params [N_PARAMS], sh_c
    [N_SH_CONSTS]. Outputs (written for every pair; culled pairs get radii 0 and zeros, colour ``max(offset, 0)``,
    opacity ``opacity`` in classic mode and 0 in antialiased mode, as the reference): radii [C,N,2] int32,
    means2d [C,N,2], depths [C,N], conics [C,N,3], compensations [C,N], opacities_c [C,N], colors [C,N,3] (when
    ``sh_degree >= 0``), bad [N] uint8 (BAD_* bits of the inputs holding NaN/inf: means, quats, scales and
    opacities of every Gaussian; SH coefficients where they are read, i.e. the active degrees of kept pairs).
    """
    n_cams = viewmats.shape[0]
    n_gauss = means.shape[0]
    n_sh_cams = sh_dc.shape[0]
    eps2d = params[P_EPS2D]
    near = params[P_NEAR]
    far = params[P_FAR]
    radius_clip = params[P_RADIUS_CLIP]
    alpha_threshold = params[P_ALPHA_THRESHOLD]
    extent_sigma = params[P_EXTENT_SIGMA]
    radius_max = params[P_RADIUS_MAX]
    offset = params[P_COLOR_OFFSET]
    width = params[P_WIDTH]
    height = params[P_HEIGHT]
    n_bases = (sh_degree + 1) * (sh_degree + 1)
    for n in prange(n_gauss):
        mx = np.float64(means[n, 0])
        my = np.float64(means[n, 1])
        mz = np.float64(means[n, 2])
        qw = np.float64(quats[n, 0])
        qx = np.float64(quats[n, 1])
        qy = np.float64(quats[n, 2])
        qz = np.float64(quats[n, 3])
        sx = np.float64(scales[n, 0])
        sy = np.float64(scales[n, 1])
        sz = np.float64(scales[n, 2])
        opacity = np.float64(opacities[n])
        flags = 0
        if not (math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz)):
            flags |= BAD_MEANS
        if not (math.isfinite(qw) and math.isfinite(qx) and math.isfinite(qy) and math.isfinite(qz)):
            flags |= BAD_QUATS
        if not (math.isfinite(sx) and math.isfinite(sy) and math.isfinite(sz)):
            flags |= BAD_SCALES
        if not math.isfinite(opacity):
            flags |= BAD_OPACITIES
        bad[n] = flags
        inv_norm = 1.0 / max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), NORM_EPS)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_to_rotmat(qw * inv_norm, qx * inv_norm, qy * inv_norm,
                                                                      qz * inv_norm)
        # covariance factor M = R diag(s)
        m00, m01, m02 = r00 * sx, r01 * sy, r02 * sz
        m10, m11, m12 = r10 * sx, r11 * sy, r12 * sz
        m20, m21, m22 = r20 * sx, r21 * sy, r22 * sz
        for c in range(n_cams):
            radii[c, n, 0] = 0
            radii[c, n, 1] = 0
            means2d[c, n, 0] = 0.0
            means2d[c, n, 1] = 0.0
            depths[c, n] = 0.0
            conics[c, n, 0] = 0.0
            conics[c, n, 1] = 0.0
            conics[c, n, 2] = 0.0
            compensations[c, n] = 0.0
            opacities_c[c, n] = 0.0 if antialiased else opacity
            if sh_degree >= 0:
                for ch in range(3):
                    colors[c, n, ch] = max(offset, 0.0)
            w00, w01, w02 = viewmats[c, 0, 0], viewmats[c, 0, 1], viewmats[c, 0, 2]
            w10, w11, w12 = viewmats[c, 1, 0], viewmats[c, 1, 1], viewmats[c, 1, 2]
            w20, w21, w22 = viewmats[c, 2, 0], viewmats[c, 2, 1], viewmats[c, 2, 2]
            x = w00 * mx + w01 * my + w02 * mz + viewmats[c, 0, 3]
            y = w10 * mx + w11 * my + w12 * mz + viewmats[c, 1, 3]
            z = w20 * mx + w21 * my + w22 * mz + viewmats[c, 2, 3]
            if not (z >= near and z <= far and z > 0.0):
                continue
            fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = _camera(viewmats, Ks, c, params)
            # camera-space factor Mc = W M, rows 0 and 1 combined with row 2 by the EWA Jacobian
            a0_ = w00 * m00 + w01 * m10 + w02 * m20
            a1_ = w00 * m01 + w01 * m11 + w02 * m21
            a2_ = w00 * m02 + w01 * m12 + w02 * m22
            b0_ = w10 * m00 + w11 * m10 + w12 * m20
            b1_ = w10 * m01 + w11 * m11 + w12 * m21
            b2_ = w10 * m02 + w11 * m12 + w12 * m22
            c0_ = w20 * m00 + w21 * m10 + w22 * m20
            c1_ = w20 * m01 + w21 * m11 + w22 * m21
            c2_ = w20 * m02 + w21 * m12 + w22 * m22
            rz = 1.0 / z
            tx = z * min(lim_x_pos, max(-lim_x_neg, x * rz))
            ty = z * min(lim_y_pos, max(-lim_y_neg, y * rz))
            ja = fx * rz
            jb = fx * tx * rz * rz
            jc = fy * rz
            jd = fy * ty * rz * rz
            jx0 = ja * a0_ - jb * c0_
            jx1 = ja * a1_ - jb * c1_
            jx2 = ja * a2_ - jb * c2_
            jy0 = jc * b0_ - jd * c0_
            jy1 = jc * b1_ - jd * c1_
            jy2 = jc * b2_ - jd * c2_
            cov_a = jx0 * jx0 + jx1 * jx1 + jx2 * jx2
            cov_b = jx0 * jy0 + jx1 * jy1 + jx2 * jy2
            cov_c = jy0 * jy0 + jy1 * jy1 + jy2 * jy2
            u = fx * x * rz + cx
            v = fy * y * rz + cy
            det_orig = cov_a * cov_c - cov_b * cov_b
            a = cov_a + eps2d
            cc = cov_c + eps2d
            det = a * cc - cov_b * cov_b
            if not det > 0.0:
                continue
            comp = 1.0
            if antialiased:
                ratio = det_orig / det
                comp = math.sqrt(ratio) if ratio > 0.0 else 0.0
            op = opacity * comp
            if not op >= alpha_threshold:
                continue
            extent = min(extent_sigma, math.sqrt(2.0 * math.log(max(op, alpha_threshold) / alpha_threshold)))
            rx = math.ceil(extent * math.sqrt(max(a, 0.0)))
            ry = math.ceil(extent * math.sqrt(max(cc, 0.0)))
            if rx <= radius_clip and ry <= radius_clip:
                continue
            if u + rx <= 0.0 or u - rx >= width or v + ry <= 0.0 or v - ry >= height:
                continue
            radii[c, n, 0] = np.int32(min(rx, radius_max))
            radii[c, n, 1] = np.int32(min(ry, radius_max))
            means2d[c, n, 0] = u
            means2d[c, n, 1] = v
            depths[c, n] = z
            conics[c, n, 0] = cc / det
            conics[c, n, 1] = -cov_b / det
            conics[c, n, 2] = a / det
            if antialiased:
                compensations[c, n] = comp
                opacities_c[c, n] = op
            if sh_degree >= 0 and rx > 0 and ry > 0:
                cs = c if n_sh_cams > 1 else 0
                dx = mx - campos[c, 0]
                dy = my - campos[c, 1]
                dz = mz - campos[c, 2]
                inv_d = 1.0 / max(math.sqrt(dx * dx + dy * dy + dz * dz), NORM_EPS)
                dx *= inv_d
                dy *= inv_d
                dz *= inv_d
                bases = _sh_bases_all(dx, dy, dz, sh_c)
                r = _sh_dot(sh_dc, sh_rest, cs, n, 0, n_bases, bases)
                g = _sh_dot(sh_dc, sh_rest, cs, n, 1, n_bases, bases)
                bl = _sh_dot(sh_dc, sh_rest, cs, n, 2, n_bases, bases)
                # a NaN/inf coefficient of the active degrees makes its channel's sum non-finite (no cancellation
                # can make it finite): the check costs one test per kept pair instead of a pass over every coefficient
                if not (math.isfinite(r) and math.isfinite(g) and math.isfinite(bl)):
                    bad[n] |= BAD_COLORS
                colors[c, n, 0] = max(r + offset, 0.0)
                colors[c, n, 1] = max(g + offset, 0.0)
                colors[c, n, 2] = max(bl + offset, 0.0)


@njit(parallel=True, cache=True, fastmath=False)
def project_sh_bwd(means, quats, scales, opacities, sh_dc, sh_rest, viewmats, Ks, campos, params, sh_c, antialiased, sh_degree,
                   radii, v_means2d, v_depths, v_conics, v_opacities_c, v_colors, want_camera_grads,
                   v_means, v_quats, v_scales, v_opacities, v_sh_dc, v_sh_rest, v_viewmats_parts, v_campos_parts):
    """Backward of :func:`project_sh_fwd` for the pairs it kept (radii > 0); culled pairs get no gradient.

    Upstream gradients: v_means2d [C,N,2], v_depths [C,N], v_conics [C,N,3], v_opacities_c [C,N], v_colors [C,N,3].
    Outputs (any float dtype, every entry written here): v_means [N,3], v_quats [N,4], v_scales [N,3],
    v_opacities [N], v_sh_dc [Cs,N,1,3], v_sh_rest [Cs,N,K-1,3]; with ``want_camera_grads`` the per-pair contributions v_viewmats_parts
    [C,N,12] (W row-major, then t) and v_campos_parts [C,N,3] (zero-initialised by the caller, culled pairs are
    skipped), summed over N by the caller.
    """
    n_cams = viewmats.shape[0]
    n_gauss = means.shape[0]
    n_sh_cams = sh_dc.shape[0]
    eps2d = params[P_EPS2D]
    offset = params[P_COLOR_OFFSET]
    n_bases = (sh_degree + 1) * (sh_degree + 1)
    for n in prange(n_gauss):
        mx = np.float64(means[n, 0])
        my = np.float64(means[n, 1])
        mz = np.float64(means[n, 2])
        qw = np.float64(quats[n, 0])
        qx = np.float64(quats[n, 1])
        qy = np.float64(quats[n, 2])
        qz = np.float64(quats[n, 3])
        sx = np.float64(scales[n, 0])
        sy = np.float64(scales[n, 1])
        sz = np.float64(scales[n, 2])
        opacity = np.float64(opacities[n])
        for cs in range(n_sh_cams):  # v_sh_* come uninitialised: each Gaussian's rows are zeroed by its thread
            for k in range(sh_dc.shape[2]):
                for ch in range(3):
                    v_sh_dc[cs, n, k, ch] = 0.0
            for k in range(sh_rest.shape[2]):
                for ch in range(3):
                    v_sh_rest[cs, n, k, ch] = 0.0
        q_norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        inv_norm = 1.0 / max(q_norm, NORM_EPS)
        nw, nx, ny, nz = qw * inv_norm, qx * inv_norm, qy * inv_norm, qz * inv_norm
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_to_rotmat(nw, nx, ny, nz)
        m00, m01, m02 = r00 * sx, r01 * sy, r02 * sz
        m10, m11, m12 = r10 * sx, r11 * sy, r12 * sz
        m20, m21, m22 = r20 * sx, r21 * sy, r22 * sz
        # gradient accumulators over cameras: means, M (covariance factor), opacity
        g_mx = 0.0
        g_my = 0.0
        g_mz = 0.0
        gm00 = gm01 = gm02 = gm10 = gm11 = gm12 = gm20 = gm21 = gm22 = 0.0
        g_op = 0.0
        for c in range(n_cams):
            if not antialiased:
                # classic mode: opacities_c is the opacity itself for every pair, culled or not
                g_op += v_opacities_c[c, n]
            if not (radii[c, n, 0] > 0 or radii[c, n, 1] > 0):
                continue
            w00, w01, w02 = viewmats[c, 0, 0], viewmats[c, 0, 1], viewmats[c, 0, 2]
            w10, w11, w12 = viewmats[c, 1, 0], viewmats[c, 1, 1], viewmats[c, 1, 2]
            w20, w21, w22 = viewmats[c, 2, 0], viewmats[c, 2, 1], viewmats[c, 2, 2]
            x = w00 * mx + w01 * my + w02 * mz + viewmats[c, 0, 3]
            y = w10 * mx + w11 * my + w12 * mz + viewmats[c, 1, 3]
            z = w20 * mx + w21 * my + w22 * mz + viewmats[c, 2, 3]
            fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = _camera(viewmats, Ks, c, params)
            a0_ = w00 * m00 + w01 * m10 + w02 * m20
            a1_ = w00 * m01 + w01 * m11 + w02 * m21
            a2_ = w00 * m02 + w01 * m12 + w02 * m22
            b0_ = w10 * m00 + w11 * m10 + w12 * m20
            b1_ = w10 * m01 + w11 * m11 + w12 * m21
            b2_ = w10 * m02 + w11 * m12 + w12 * m22
            c0_ = w20 * m00 + w21 * m10 + w22 * m20
            c1_ = w20 * m01 + w21 * m11 + w22 * m21
            c2_ = w20 * m02 + w21 * m12 + w22 * m22
            rz = 1.0 / z
            ux = x * rz
            uy = y * rz
            clx = min(lim_x_pos, max(-lim_x_neg, ux))
            cly = min(lim_y_pos, max(-lim_y_neg, uy))
            tx = z * clx
            ty = z * cly
            ja = fx * rz
            jb = fx * tx * rz * rz
            jc = fy * rz
            jd = fy * ty * rz * rz
            jx0 = ja * a0_ - jb * c0_
            jx1 = ja * a1_ - jb * c1_
            jx2 = ja * a2_ - jb * c2_
            jy0 = jc * b0_ - jd * c0_
            jy1 = jc * b1_ - jd * c1_
            jy2 = jc * b2_ - jd * c2_
            cov_a = jx0 * jx0 + jx1 * jx1 + jx2 * jx2
            cov_b = jx0 * jy0 + jx1 * jy1 + jx2 * jy2
            cov_c = jy0 * jy0 + jy1 * jy1 + jy2 * jy2
            a = cov_a + eps2d
            cc = cov_c + eps2d
            det = a * cc - cov_b * cov_b
            # --- opacity and compensation
            v_op_c = v_opacities_c[c, n]
            v_a = 0.0
            v_b = 0.0
            v_c = 0.0
            if antialiased:
                det_orig = cov_a * cov_c - cov_b * cov_b
                ratio = det_orig / det
                comp = math.sqrt(ratio) if ratio > 0.0 else 0.0
                g_op += v_op_c * comp
                if ratio > 0.0:
                    v_ratio = v_op_c * opacity * 0.5 / comp
                    v_det_orig = v_ratio / det
                    v_det_c = -v_ratio * ratio / det
                    v_a += v_det_orig * cov_c + v_det_c * cc
                    v_c += v_det_orig * cov_a + v_det_c * a
                    v_b += -2.0 * cov_b * (v_det_orig + v_det_c)
            # --- conic = (cc, -b, a) / det
            p = cc / det
            q = -cov_b / det
            r = a / det
            v_p = v_conics[c, n, 0]
            v_q = v_conics[c, n, 1]
            v_r = v_conics[c, n, 2]
            v_det = -(v_p * p + v_q * q + v_r * r) / det
            v_a += v_r / det + v_det * cc
            v_b += -v_q / det - 2.0 * cov_b * v_det
            v_c += v_p / det + v_det * a
            # --- cov2d = (J Mc)(J Mc)^T
            v_jx0 = 2.0 * v_a * jx0 + v_b * jy0
            v_jx1 = 2.0 * v_a * jx1 + v_b * jy1
            v_jx2 = 2.0 * v_a * jx2 + v_b * jy2
            v_jy0 = 2.0 * v_c * jy0 + v_b * jx0
            v_jy1 = 2.0 * v_c * jy1 + v_b * jx1
            v_jy2 = 2.0 * v_c * jy2 + v_b * jx2
            v_a0_ = ja * v_jx0
            v_a1_ = ja * v_jx1
            v_a2_ = ja * v_jx2
            v_b0_ = jc * v_jy0
            v_b1_ = jc * v_jy1
            v_b2_ = jc * v_jy2
            v_c0_ = -jb * v_jx0 - jd * v_jy0
            v_c1_ = -jb * v_jx1 - jd * v_jy1
            v_c2_ = -jb * v_jx2 - jd * v_jy2
            v_ja = v_jx0 * a0_ + v_jx1 * a1_ + v_jx2 * a2_
            v_jb = -(v_jx0 * c0_ + v_jx1 * c1_ + v_jx2 * c2_)
            v_jc = v_jy0 * b0_ + v_jy1 * b1_ + v_jy2 * b2_
            v_jd = -(v_jy0 * c0_ + v_jy1 * c1_ + v_jy2 * c2_)
            # ja = fx rz, jb = fx tx rz^2, jc = fy rz, jd = fy ty rz^2
            v_rz = fx * v_ja + fy * v_jc + 2.0 * fx * tx * rz * v_jb + 2.0 * fy * ty * rz * v_jd
            v_tx = fx * rz * rz * v_jb
            v_ty = fy * rz * rz * v_jd
            # means2d = (fx x rz + cx, fy y rz + cy), depth = z
            v_u = v_means2d[c, n, 0]
            v_v = v_means2d[c, n, 1]
            v_x = fx * rz * v_u
            v_y = fy * rz * v_v
            v_rz += fx * x * v_u + fy * y * v_v
            v_z = v_depths[c, n]
            # tx = z clamp(x rz): the clamp passes the gradient strictly inside (half of it at a tie, as torch)
            v_z += v_tx * clx + v_ty * cly
            v_ux = v_tx * z
            v_uy = v_ty * z
            wx = 1.0 if (-lim_x_neg < ux < lim_x_pos) else (0.5 if (ux == -lim_x_neg or ux == lim_x_pos) else 0.0)
            wy = 1.0 if (-lim_y_neg < uy < lim_y_pos) else (0.5 if (uy == -lim_y_neg or uy == lim_y_pos) else 0.0)
            v_ux *= wx
            v_uy *= wy
            v_x += v_ux * rz
            v_y += v_uy * rz
            v_rz += v_ux * x + v_uy * y
            v_z += -v_rz * rz * rz
            # mean_c = W mu + t; Mc = W M
            g_mx += w00 * v_x + w10 * v_y + w20 * v_z
            g_my += w01 * v_x + w11 * v_y + w21 * v_z
            g_mz += w02 * v_x + w12 * v_y + w22 * v_z
            gm00 += w00 * v_a0_ + w10 * v_b0_ + w20 * v_c0_
            gm01 += w00 * v_a1_ + w10 * v_b1_ + w20 * v_c1_
            gm02 += w00 * v_a2_ + w10 * v_b2_ + w20 * v_c2_
            gm10 += w01 * v_a0_ + w11 * v_b0_ + w21 * v_c0_
            gm11 += w01 * v_a1_ + w11 * v_b1_ + w21 * v_c1_
            gm12 += w01 * v_a2_ + w11 * v_b2_ + w21 * v_c2_
            gm20 += w02 * v_a0_ + w12 * v_b0_ + w22 * v_c0_
            gm21 += w02 * v_a1_ + w12 * v_b1_ + w22 * v_c1_
            gm22 += w02 * v_a2_ + w12 * v_b2_ + w22 * v_c2_
            if want_camera_grads:
                # v_W = v_mean_c mu^T + v_Mc M^T
                v_viewmats_parts[c, n, 0] = v_x * mx + v_a0_ * m00 + v_a1_ * m01 + v_a2_ * m02
                v_viewmats_parts[c, n, 1] = v_x * my + v_a0_ * m10 + v_a1_ * m11 + v_a2_ * m12
                v_viewmats_parts[c, n, 2] = v_x * mz + v_a0_ * m20 + v_a1_ * m21 + v_a2_ * m22
                v_viewmats_parts[c, n, 3] = v_y * mx + v_b0_ * m00 + v_b1_ * m01 + v_b2_ * m02
                v_viewmats_parts[c, n, 4] = v_y * my + v_b0_ * m10 + v_b1_ * m11 + v_b2_ * m12
                v_viewmats_parts[c, n, 5] = v_y * mz + v_b0_ * m20 + v_b1_ * m21 + v_b2_ * m22
                v_viewmats_parts[c, n, 6] = v_z * mx + v_c0_ * m00 + v_c1_ * m01 + v_c2_ * m02
                v_viewmats_parts[c, n, 7] = v_z * my + v_c0_ * m10 + v_c1_ * m11 + v_c2_ * m12
                v_viewmats_parts[c, n, 8] = v_z * mz + v_c0_ * m20 + v_c1_ * m21 + v_c2_ * m22
                v_viewmats_parts[c, n, 9] = v_x
                v_viewmats_parts[c, n, 10] = v_y
                v_viewmats_parts[c, n, 11] = v_z
            # --- colours from SH (only pairs with both radii > 0 have a colour, as the reference's mask)
            if sh_degree >= 0 and radii[c, n, 0] > 0 and radii[c, n, 1] > 0:
                cs = c if n_sh_cams > 1 else 0
                dx = mx - campos[c, 0]
                dy = my - campos[c, 1]
                dz = mz - campos[c, 2]
                d_norm = math.sqrt(dx * dx + dy * dy + dz * dz)
                inv_d = 1.0 / max(d_norm, NORM_EPS)
                ex = dx * inv_d
                ey = dy * inv_d
                ez = dz * inv_d
                bases = _sh_bases_all(ex, ey, ez, sh_c)
                sum_r = _sh_dot(sh_dc, sh_rest, cs, n, 0, n_bases, bases)
                sum_g = _sh_dot(sh_dc, sh_rest, cs, n, 1, n_bases, bases)
                sum_b = _sh_dot(sh_dc, sh_rest, cs, n, 2, n_bases, bases)
                # clamp_min(colour + offset, 0) passes the gradient where the input is >= 0
                v_r = v_colors[c, n, 0] if sum_r + offset >= 0.0 else 0.0
                v_g = v_colors[c, n, 1] if sum_g + offset >= 0.0 else 0.0
                v_bl = v_colors[c, n, 2] if sum_b + offset >= 0.0 else 0.0
                _sh_scatter(v_sh_dc, v_sh_rest, cs, n, 0, n_bases, bases, v_r)
                _sh_scatter(v_sh_dc, v_sh_rest, cs, n, 1, n_bases, bases, v_g)
                _sh_scatter(v_sh_dc, v_sh_rest, cs, n, 2, n_bases, bases, v_bl)
                v_ex, v_ey, v_ez = _sh_dir_vjp(sh_rest, cs, n, n_bases, ex, ey, ez, v_r, v_g, v_bl, sh_c)
                # normalization dir / max(|dir|, eps)
                if d_norm > NORM_EPS:
                    dot = ex * v_ex + ey * v_ey + ez * v_ez
                    v_dx = (v_ex - ex * dot) * inv_d
                    v_dy = (v_ey - ey * dot) * inv_d
                    v_dz = (v_ez - ez * dot) * inv_d
                else:
                    v_dx = v_ex * inv_d
                    v_dy = v_ey * inv_d
                    v_dz = v_ez * inv_d
                g_mx += v_dx
                g_my += v_dy
                g_mz += v_dz
                if want_camera_grads:
                    v_campos_parts[c, n, 0] = -v_dx
                    v_campos_parts[c, n, 1] = -v_dy
                    v_campos_parts[c, n, 2] = -v_dz
        v_means[n, 0] = g_mx
        v_means[n, 1] = g_my
        v_means[n, 2] = g_mz
        v_opacities[n] = g_op
        # M = R diag(s)
        v_scales[n, 0] = gm00 * r00 + gm10 * r10 + gm20 * r20
        v_scales[n, 1] = gm01 * r01 + gm11 * r11 + gm21 * r21
        v_scales[n, 2] = gm02 * r02 + gm12 * r12 + gm22 * r22
        g00, g01, g02 = gm00 * sx, gm01 * sy, gm02 * sz
        g10, g11, g12 = gm10 * sx, gm11 * sy, gm12 * sz
        g20, g21, g22 = gm20 * sx, gm21 * sy, gm22 * sz
        v_nw = 2.0 * (-nz * g01 + ny * g02 + nz * g10 - nx * g12 - ny * g20 + nx * g21)
        v_nx = 2.0 * (ny * g01 + nz * g02 + ny * g10 - 2.0 * nx * g11 - nw * g12 + nz * g20 + nw * g21 - 2.0 * nx * g22)
        v_ny = 2.0 * (-2.0 * ny * g00 + nx * g01 + nw * g02 + nx * g10 + nz * g12 - nw * g20 + nz * g21
                      - 2.0 * ny * g22)
        v_nz = 2.0 * (-2.0 * nz * g00 - nw * g01 + nx * g02 + nw * g10 - 2.0 * nz * g11 + ny * g12 + nx * g20
                      + ny * g21)
        # q / max(|q|, eps)
        if q_norm > NORM_EPS:
            dot = nw * v_nw + nx * v_nx + ny * v_ny + nz * v_nz
            v_nw -= nw * dot
            v_nx -= nx * dot
            v_ny -= ny * dot
            v_nz -= nz * dot
        v_quats[n, 0] = v_nw * inv_norm
        v_quats[n, 1] = v_nx * inv_norm
        v_quats[n, 2] = v_ny * inv_norm
        v_quats[n, 3] = v_nz * inv_norm
