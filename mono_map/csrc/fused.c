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
