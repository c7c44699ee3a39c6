/* The fused surface's snap (mono_map.mapping.fused.SurfaceFusion.snap_depths loads it): each pixel's samples
   along its ray, then the TSDF's zero crossing nearest the pixel's own depth, in two passes around open3d's
   hash-map lookup of the samples' blocks. The float64 operations of the numpy form, in its order (built
   without fused multiply-adds). */
#include <math.h>
#include <stdint.h>

#define BLOCK 8

/* Pass 1. Pixel p (column u[p], row v[p], depth z0[p] metres) gets s samples at depths z0 + offs[j] (zs, p-major);
   each sample's world point (k: 3x3 intrinsics of the pixel grid, t: T_world_cam's 3x4 rows) lies in the
   cell floor(point / res): its block coordinates (blk, 3 int32 each) and its index in the 8^3 block (loc:
   x + 8 y + 64 z); step: how far the cell's value, which holds at the cell's centre, moves to the sample —
   along the camera's axis (the sample's depth minus the centre's), or with nw (p x 3 world unit normals, may
   be NULL) minus the sample's offset from the centre along the pixel's normal. */
void mm_snap_samples(int64_t n, const int64_t *u, const int64_t *v, const double *z0, int64_t s, const double *offs,
                     const double *k, const double *t, const double *nw, double res, int32_t *blk, int32_t *loc,
                     double *zs, double *step) {
    const double fx = k[0], cx = k[2], fy = k[4], cy = k[5];
    for (int64_t p = 0; p < n; p++) {
        const double du = ((double)u[p] - cx) / fx, dv = ((double)v[p] - cy) / fy;
        for (int64_t j = 0; j < s; j++) {
            const int64_t q = p * s + j;
            const double z = z0[p] + offs[j];
            const double x = du * z, y = dv * z;
            double pt[3], c[3];
            int64_t lat[3];
            for (int r = 0; r < 3; r++) {
                double acc = x * t[4 * r];
                acc += y * t[4 * r + 1];
                acc += z * t[4 * r + 2];
                pt[r] = acc + t[4 * r + 3];
                const double f = floor(pt[r] / res);
                lat[r] = (int64_t)f;
                c[r] = (f + 0.5) * res;
                const int64_t b = lat[r] >> 3;            /* floor division by the block size */
                blk[3 * q + r] = (int32_t)b;
                lat[r] -= b * BLOCK;
            }
            loc[q] = (int32_t)(lat[0] + BLOCK * lat[1] + BLOCK * BLOCK * lat[2]);
            zs[q] = z;
            if (nw == 0) {          /* the centre's depth in this camera: (c - origin) . axis */
                double zc = (c[0] - t[3]) * t[2];
                zc += (c[1] - t[7]) * t[6];
                zc += (c[2] - t[11]) * t[10];
                step[q] = z - zc;
            } else {
                const double *m = nw + 3 * p;
                double d = (pt[0] - c[0]) * m[0];
                d += (pt[1] - c[1]) * m[1];
                d += (pt[2] - c[2]) * m[2];
                step[q] = -d;
            }
        }
    }
}

/* Pass 2. With each sample's block slot (buf, -1 where the block does not exist), read its cell's tsdf and
   summed weight (open3d's attribute buffers, 512 voxels a block), scale the tsdf by trunc_max and move it by
   step; the crossing from >= 0 to < 0 between two consecutive samples whose weights are >= thr and depths > 0,
   nearest to the middle sample (index mid; the first of equally near ones) gives the pixel's depth by linear
   interpolation (out, float32; 0 where none). */
void mm_snap_cross(int64_t n, int64_t s, const int64_t *buf, const int32_t *loc, const double *zs,
                   const double *step, const float *tsdf, const float *weight, float trunc_max, float thr,
                   int64_t mid, float *out) {
    for (int64_t p = 0; p < n; p++) {
        const int64_t o = p * s;
        double best = INFINITY, zc = 0.0;
        double t_prev = 0.0;
        int good_prev = 0;
        for (int64_t j = 0; j < s; j++) {
            const int64_t q = o + j;
            float tv = 0.0f, wv = 0.0f;
            if (buf[q] >= 0) {
                const int64_t idx = buf[q] * (BLOCK * BLOCK * BLOCK) + loc[q];
                tv = tsdf[idx];
                wv = weight[idx];
            }
            const double tt = (double)(tv * trunc_max) - step[q];
            const int good = (wv >= thr) && (zs[q] > 0);
            if (j > 0 && good_prev && good && t_prev >= 0 && tt < 0) {
                const double dist = fabs((double)(j - 1) + 0.5 - (double)mid);
                if (dist < best) {
                    best = dist;
                    const double den = t_prev - tt;
                    zc = zs[q - 1] + (zs[q] - zs[q - 1]) * (t_prev / (den > 0 ? den : 1.0));
                }
            }
            t_prev = tt;
            good_prev = good;
        }
        out[p] = isfinite(best) ? (float)zc : 0.0f;
    }
}

/* The TSDF update of one frame (SurfaceFusion.integrate without the sub-pixel depth): voxel j at vc (n x 3 world
   lattice points, float32) with flattened index idx[j] moves into the camera (pc = R vc + t, the cell's centre;
   float32), projects to the nearest pixel (kf: fx, cx, fy, cy as float32; rint: half to even) of the h x w grid,
   and where it is in front, inside the image, the pixel has a depth d > 0 and the signed distance
   sdf >= -trunc_behind * tau (the pixel's band) its tsdf and summed weight get clip(sdf, -tau, tau) / trunc_max
   with the pixel's weight. sdf = d - z along the axis, or with normals (h x w x 3, float32; may be NULL) the
   distance of the centre to the plane through the pixel's surface point (k: the grid's 3x3 intrinsics, float64).
   Returns the number of voxels updated. */
int64_t mm_tsdf_update(int64_t n, const float *vc, const int64_t *idx, const float *r, const float *t,
                       const float *kf, const double *k, const float *depth, const float *trunc, const float *weight,
                       const float *normals, int64_t h, int64_t w, float neg_behind, double trunc_max, float *tsdf,
                       float *wsum) {
    int64_t count = 0;
    const double fx = k[0], skew = k[1], cx = k[2], fy = k[4], cy = k[5];
    for (int64_t j = 0; j < n; j++) {
        const float *p = vc + 3 * j;
        float pc[3];
        for (int q = 0; q < 3; q++) pc[q] = (p[0] * r[3 * q] + p[1] * r[3 * q + 1] + p[2] * r[3 * q + 2]) + t[q];
        const float z = pc[2];
        if (!(z > 1e-3f)) continue;
        const float uf = rintf(kf[0] * pc[0] / z + kf[1]), vf = rintf(kf[2] * pc[1] / z + kf[3]);
        if (!(uf >= 0.0f && uf < (float)w && vf >= 0.0f && vf < (float)h)) continue;
        const int64_t pix = (int64_t)vf * w + (int64_t)uf;
        const float d = depth[pix], tau = trunc[pix];
        if (!(d > 0.0f)) continue;
        float t_new;
        if (normals == 0) {
            const float sdf = d - z;
            if (!(sdf >= neg_behind * tau)) continue;
            const float c = sdf < -tau ? -tau : (sdf > tau ? tau : sdf);
            t_new = c / (float)trunc_max;
        } else {
            const double zz = (double)d;
            const double y = ((double)vf - cy) / fy * zz;
            const double x = (((double)uf - cx) * zz - skew * y) / fx;
            const float *m = normals + 3 * pix;
            double sdf = (double)m[0] * ((double)pc[0] - x);
            sdf += (double)m[1] * ((double)pc[1] - y);
            sdf += (double)m[2] * ((double)pc[2] - zz);
            if (!(sdf >= (double)(neg_behind * tau))) continue;
            const double c = sdf < -(double)tau ? -(double)tau : (sdf > (double)tau ? (double)tau : sdf);
            t_new = (float)(c / trunc_max);
        }
        const float wg = weight[pix];
        const int64_t i = idx[j];
        const float w_old = wsum[i], w_new = w_old + wg;
        tsdf[i] = (tsdf[i] * w_old + t_new * wg) / (w_new > 0.0f ? w_new : 1.0f);
        wsum[i] = w_new;
        count++;
    }
    return count;
}
