/* The plane sweep's cost (mono_map.depth.sweep_c loads it; the torch form is mono_map.depth.multiview.sweep_cost):
   every source image warped into the target through fronto-parallel planes (one homography per plane, torch's
   grid_sample: bilinear, border padding, pixel centres) and compared with monodepth2's SSIM + L1 over 3x3
   windows (reflection-padded), the minimum over the sources per plane and pixel. One plane at a time, in
   float32, the torch form's operations in its order where it has one (built without fused multiply-adds). */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* IEEE results unchanged; lets the compiler vectorise the clamps and selects (no code here reads FP flags) */
#pragma GCC optimize("no-trapping-math")

static inline int64_t reflect(int64_t i, int64_t n) { return i < 0 ? -i : (i >= n ? 2 * n - 2 - i : i); }

/* 3x3 window means of x (h x w) with reflection padding, as photometric.box3: rows first, then columns, / 9 */
static void box3(const float *x, float *tmp, float *out, int64_t h, int64_t w) {
    for (int64_t v = 0; v < h; v++) {
        const float *a = x + reflect(v - 1, h) * w, *b = x + v * w, *c = x + reflect(v + 1, h) * w;
        float *t = tmp + v * w;
        for (int64_t u = 0; u < w; u++) t[u] = a[u] + b[u] + c[u];
    }
    for (int64_t v = 0; v < h; v++) {
        const float *t = tmp + v * w;
        float *o = out + v * w;
        o[0] = (t[1] + t[0] + t[1]) / 9.0f;
        for (int64_t u = 1; u < w - 1; u++) o[u] = (t[u - 1] + t[u] + t[u + 1]) / 9.0f;
        o[w - 1] = (t[w - 2] + t[w - 1] + t[w - 2]) / 9.0f;
    }
}

typedef struct {
    int64_t h, w;
    const float *y, *mu_y, *syy;       /* the target and its window statistics */
    float *xx, *xy, *tmp, *mu_x, *exx, *exy;
} Ssim;

/* err = 0.85 (1 - SSIM)/2 + 0.15 |x - y| per pixel (multiview.ssim_l1_against) */
static void ssim_l1(Ssim *s, const float *x, float *err) {
    const int64_t n = s->h * s->w;
    const float C1 = 0.01f * 0.01f, C2 = 0.03f * 0.03f;
    for (int64_t i = 0; i < n; i++) {
        s->xx[i] = x[i] * x[i];
        s->xy[i] = x[i] * s->y[i];
    }
    box3(x, s->tmp, s->mu_x, s->h, s->w);
    box3(s->xx, s->tmp, s->exx, s->h, s->w);
    box3(s->xy, s->tmp, s->exy, s->h, s->w);
    for (int64_t i = 0; i < n; i++) {
        const float mx = s->mu_x[i], my = s->mu_y[i];
        const float sxx = s->exx[i] - mx * mx;
        const float sxy = s->exy[i] - mx * my;
        const float num = (2.0f * mx * my + C1) * (2.0f * sxy + C2);
        const float den = (mx * mx + my * my + C1) * (sxx + s->syy[i] + C2);
        float d = (1.0f - num / den) / 2.0f;
        d = d < 0.0f ? 0.0f : (d > 1.0f ? 1.0f : d);
        err[i] = 0.85f * d + 0.15f * fabsf(x[i] - s->y[i]);
    }
}

/* src (h x w) seen through the plane with inverse depth inv_d: p_src ~ M p + bt inv_d (M = K R K^-1, bt = K t);
   warped (h x w) and valid (in front of the source camera, inside its image). Two loops: the sampling positions
   (vectorised: no gathers; the clipped position is >= 0, so truncation is floor), then the bilinear reads. */
static void plane_warp(const float *src, int64_t h, int64_t w, const float *m, const float *bt, float inv_d,
                       float *warped, int32_t *valid, float *pos_x, float *pos_y) {
    const float fw = (float)w, fh = (float)h, xmax = (float)(w - 1), ymax = (float)(h - 1);
    const float b0 = bt[0] * inv_d, b1 = bt[1] * inv_d, b2 = bt[2] * inv_d;
    for (int64_t v = 0; v < h; v++) {
        const float fv = (float)v;
        float *px = pos_x + v * w, *py = pos_y + v * w;
        int32_t *ok = valid + v * w;
        for (int32_t u = 0; u < (int32_t)w; u++) {
            const float fu = (float)u;               /* (M p) + bt inv_d, M p summed in column order */
            const float p0 = (m[0] * fu + m[1] * fv + m[2]) + b0;
            const float p1 = (m[3] * fu + m[4] * fv + m[5]) + b1;
            const float z = (m[6] * fu + m[7] * fv + m[8]) + b2;
            const float zc = z > 1e-6f ? z : 1e-6f;
            const float gx = (2.0f * p0 / zc + 1.0f) / fw - 1.0f;
            const float gy = (2.0f * p1 / zc + 1.0f) / fh - 1.0f;
            ok[u] = (z > 0.0f) & (fabsf(gx) <= 1.0f) & (fabsf(gy) <= 1.0f);
            const float ix = (gx + 1.0f) * (fw / 2.0f) - 0.5f;   /* grid_sample: unnormalise, clip (border) */
            const float iy = (gy + 1.0f) * (fh / 2.0f) - 0.5f;
            px[u] = ix < 0.0f ? 0.0f : (ix > xmax ? xmax : ix);
            py[u] = iy < 0.0f ? 0.0f : (iy > ymax ? ymax : iy);
        }
    }
    for (int64_t q = 0; q < h * w; q++) {   /* grid_sample's corner weights; a corner past the edge reads 0 */
        const float ix = pos_x[q], iy = pos_y[q];
        const int32_t x0 = (int32_t)ix, y0 = (int32_t)iy;
        const float e = (float)(x0 + 1) - ix, we = ix - (float)x0, sth = (float)(y0 + 1) - iy, nth = iy - (float)y0;
        const float *r0 = src + (int64_t)y0 * w, *r1 = src + (int64_t)(y0 + 1) * w;
        const int in_x = x0 + 1 < w, in_y = y0 + 1 < h;
        const float v00 = r0[x0], v01 = in_x ? r0[x0 + 1] : 0.0f;
        const float v10 = in_y ? r1[x0] : 0.0f, v11 = in_x && in_y ? r1[x0 + 1] : 0.0f;
        warped[q] = v00 * (sth * e) + v01 * (sth * we) + v10 * (nth * e) + v11 * (nth * we);
    }
}

/* cost (n_planes x h x w): per plane the minimum over the n_src sources (each h x w, with m: n_src 3x3 row-major,
   bt: n_src x 3) of the warped source's error, INFINITY where no source sees the plane; ident (h x w): the
   minimum error of the unwarped sources. target, sources: grey in [0, 1]. Returns 0, or -1 if out of memory. */
int mm_sweep_cost(int64_t h, int64_t w, const float *target, int64_t n_src, const float *sources, const float *m,
                  const float *bt, int64_t n_planes, const float *inv_d, float *cost, float *ident) {
    const int64_t n = h * w;
    float *buf = (float *)malloc(sizeof(float) * (size_t)n * 12);
    int32_t *valid = (int32_t *)malloc(sizeof(int32_t) * (size_t)n);
    if (!buf || !valid) {
        free(buf);
        free(valid);
        return -1;
    }
    float *mu_y = buf, *syy = buf + n, *warped = buf + 2 * n, *err = buf + 3 * n;
    Ssim s = {h, w, target, mu_y, syy, buf + 4 * n, buf + 5 * n, buf + 6 * n, buf + 7 * n, buf + 8 * n, buf + 9 * n};
    /* the target's statistics: mu_y, and syy = box(y y) - mu_y^2 */
    box3(target, s.tmp, mu_y, h, w);
    for (int64_t i = 0; i < n; i++) s.xx[i] = target[i] * target[i];
    box3(s.xx, s.tmp, syy, h, w);
    for (int64_t i = 0; i < n; i++) syy[i] = syy[i] - mu_y[i] * mu_y[i];
    for (int64_t i = 0; i < n * n_planes; i++) cost[i] = INFINITY;
    for (int64_t i = 0; i < n; i++) ident[i] = INFINITY;
    for (int64_t k = 0; k < n_src; k++) {
        const float *src = sources + k * n;
        for (int64_t d = 0; d < n_planes; d++) {
            plane_warp(src, h, w, m + 9 * k, bt + 3 * k, inv_d[d], warped, valid, buf + 10 * n, buf + 11 * n);
            ssim_l1(&s, warped, err);
            float *c = cost + d * n;
            for (int64_t i = 0; i < n; i++)
                if (valid[i] && err[i] < c[i]) c[i] = err[i];
        }
        ssim_l1(&s, src, err);
        for (int64_t i = 0; i < n; i++)
            if (err[i] < ident[i]) ident[i] = err[i];
    }
    free(buf);
    free(valid);
    return 0;
}

/* multiview.windowed_cost: planes no source sees (cost INFINITY) get the pixel's mean of the seen ones, then cost
   (D x h x w) and ident (h x w) are averaged over window x window pixels (replicate padding; torch avg_pool2d's
   row-major sum, / window^2) into c_out and ident_out; informative (h x w): at least half the planes seen and the
   windowed identity above the best windowed plane. Returns 0, or -1 if out of memory. */
int mm_windowed_cost(int64_t d_planes, int64_t h, int64_t w, const float *cost, const float *ident, int64_t window,
                     float *c_out, float *ident_out, uint8_t *informative) {
    const int64_t n = h * w, r = window / 2;
    float *filled = (float *)malloc(sizeof(float) * (size_t)n * (size_t)d_planes);
    float *nseen = (float *)malloc(sizeof(float) * (size_t)n);
    float *mean = (float *)malloc(sizeof(float) * (size_t)n);
    if (!filled || !nseen || !mean) {
        free(filled);
        free(nseen);
        free(mean);
        return -1;
    }
    for (int64_t i = 0; i < n; i++) nseen[i] = 0.0f, mean[i] = 0.0f;
    for (int64_t k = 0; k < d_planes; k++) {
        const float *c = cost + k * n;
        for (int64_t i = 0; i < n; i++) {
            const int seen = isfinite(c[i]);
            nseen[i] += seen ? 1.0f : 0.0f;
            mean[i] += seen ? c[i] : 0.0f;
        }
    }
    for (int64_t i = 0; i < n; i++) mean[i] = mean[i] / (nseen[i] > 1.0f ? nseen[i] : 1.0f);
    for (int64_t k = 0; k < d_planes; k++)
        for (int64_t i = 0; i < n; i++) filled[k * n + i] = isfinite(cost[k * n + i]) ? cost[k * n + i] : mean[i];
    const float area = (float)(window * window);
    for (int64_t k = 0; k <= d_planes; k++) {          /* the planes, then the identity */
        const float *src = k < d_planes ? filled + k * n : ident;
        float *dst = k < d_planes ? c_out + k * n : ident_out;
        for (int64_t v = 0; v < h; v++)
            for (int64_t u = 0; u < w; u++) {
                float sum = 0.0f;
                for (int64_t dv = -r; dv <= r; dv++) {
                    const int64_t vv = v + dv < 0 ? 0 : (v + dv >= h ? h - 1 : v + dv);
                    for (int64_t du = -r; du <= r; du++) {
                        const int64_t uu = u + du < 0 ? 0 : (u + du >= w ? w - 1 : u + du);
                        sum += src[vv * w + uu];
                    }
                }
                dst[v * w + u] = sum / area;
            }
    }
    for (int64_t i = 0; i < n; i++) {
        float best = INFINITY;
        for (int64_t k = 0; k < d_planes; k++) best = c_out[k * n + i] < best ? c_out[k * n + i] : best;
        informative[i] = (nseen[i] * 2.0f >= (float)d_planes) && (ident_out[i] > best);
    }
    free(filled);
    free(nseen);
    free(mean);
    return 0;
}

/* multiview.resample: x (h x w x c, channels last) read with grid_sample's bilinear weights and border clipping at
   the full image's pixels (v step, u step) of an (full_h x full_w) image: out (out_h x out_w x c, channels last) */
/* grid_sample's source coordinate (align_corners false, border clipping) of output pixel i, which is pixel i step
   of a full image n_full wide, on a grid n wide covering it */
static inline float source_coordinate(int64_t i, int64_t step, int64_t n_full, int64_t n) {
    const float g = 2.0f * ((float)i * (float)step + 0.5f) / (float)n_full - 1.0f;
    const float c = (g + 1.0f) * ((float)n / 2.0f) - 0.5f;
    return c < 0.0f ? 0.0f : (c > (float)n - 1.0f ? (float)n - 1.0f : c);
}

void mm_resample(int64_t h, int64_t w, int64_t c, const float *x, int64_t out_h, int64_t out_w, int64_t full_h,
                 int64_t full_w, int64_t step, float *out) {
    for (int64_t v = 0; v < out_h; v++) {
        const float iy = source_coordinate(v, step, full_h, h);
        const int64_t y0 = (int64_t)iy;
        const float nth = iy - (float)y0, sth = (float)(y0 + 1) - iy;
        const int in_y = y0 + 1 < h;
        for (int64_t u = 0; u < out_w; u++) {
            const float ix = source_coordinate(u, step, full_w, w);
            const int64_t x0 = (int64_t)ix;
            const float we = ix - (float)x0, e = (float)(x0 + 1) - ix;
            const int in_x = x0 + 1 < w;
            const float a = sth * e, b = in_x ? sth * we : 0.0f, cc = in_y ? nth * e : 0.0f,
                        dd = in_x && in_y ? nth * we : 0.0f;
            const float *p00 = x + (y0 * w + x0) * c;
            const float *p01 = in_x ? p00 + c : p00, *p10 = in_y ? p00 + w * c : p00;
            const float *p11 = in_x && in_y ? p00 + (w + 1) * c : p00;
            float *o = out + (v * out_w + u) * c;
            for (int64_t k = 0; k < c; k++) o[k] = p00[k] * a + p01[k] * b + p10[k] * cc + p11[k] * dd;
        }
    }
}
