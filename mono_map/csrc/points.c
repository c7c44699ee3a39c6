/* Measurements -> world points (mono_map.mapping.points loads it): pixels_to_world and lidar_to_world in
   one pass over the image / scan, the float64 operations of the numpy forms in the same order (built
   without fused multiply-adds: numpy's bits). */
#include <math.h>
#include <stdint.h>

/* o = T p for a 3x4 row-major T, in rigid_columns' order: ((T0 x + T1 y) + T2 z) + T3 */
static inline void rigid(const double *t, double x, double y, double z, double *o) {
    for (int r = 0; r < 3; r++) {
        double acc = x * t[4 * r];
        acc += y * t[4 * r + 1];
        acc += z * t[4 * r + 2];
        acc += t[4 * r + 3];
        o[r] = acc;
    }
}

int64_t mm_pixels_to_world(const float *depth, const uint8_t *mask, int64_t h, int64_t w, const double *k,
                           const double *t, double *out) {
    const double fx = k[0], skew = k[1], cx = k[2], fy = k[4], cy = k[5];
    int64_t n = 0;
    for (int64_t v = 0; v < h; v++) {
        for (int64_t u = 0; u < w; u++) {
            if (!mask[v * w + u]) continue;
            const double z = (double)depth[v * w + u];
            const double y = ((double)v - cy) / fy * z;
            const double x = (((double)u - cx) * z - skew * y) / fx;
            rigid(t, x, y, z, out + 3 * n);
            n++;
        }
    }
    return n;
}

/* lidar_to_world: finite points of an (n, cols) float32 scan, optionally only those in image_2's view (camera
   frame by tcv = T_cam2_velo's 3x4, pixel = K p / z rounded half to even, as in_camera_fov), moved to the
   world by twv = T_world_velo's 3x4 with rigid_columns' operation order. */
int64_t mm_lidar_to_world(const float *scan, int64_t n, int64_t cols, int fov, const double *tcv,
                          const double *k, int64_t h, int64_t w, double min_depth, const double *twv,
                          double *out) {
    int64_t m = 0;
    for (int64_t i = 0; i < n; i++) {
        const double x = (double)scan[i * cols], y = (double)scan[i * cols + 1], z = (double)scan[i * cols + 2];
        if (!isfinite(x) || !isfinite(y) || !isfinite(z)) continue;
        if (fov) {
            double c[3];
            rigid(tcv, x, y, z, c);
            if (!(c[2] > min_depth)) continue;
            const double pu = k[0] * c[0] + k[1] * c[1] + k[2] * c[2];
            const double pv = k[3] * c[0] + k[4] * c[1] + k[5] * c[2];
            const double pw = k[6] * c[0] + k[7] * c[1] + k[8] * c[2];
            const double u = nearbyint(pu / pw), v = nearbyint(pv / pw);
            if (!(u >= 0 && u < (double)w && v >= 0 && v < (double)h)) continue;
        }
        rigid(twv, x, y, z, out + 3 * m);
        m++;
    }
    return m;
}
