"""Optional compiled kernel for the DDA of :mod:`mono_map.mapping.raycast` (same cells, ~20× faster).

The C source below is OctoMap 1.10's ``computeRayKeys`` transcribed with the same types
(``float`` points and direction, ``double`` tMax/tDelta), emitting linear box indices. It is
compiled on first use with the system C compiler into a cache directory
(``$MONO_MAP_CACHE`` or ``~/.cache/mono_map``) and loaded with ctypes. Without a compiler (or with
``MONO_MAP_NO_C=1``) the numpy implementation is used; the tests check both give the same cells.
Compiled with ``-ffp-contract=off`` and no ``-ffast-math`` so the float arithmetic is IEEE, as in
OctoMap's own build.
"""

from __future__ import annotations

import ctypes
import os
import threading

import numpy as np

from mono_map import ckernel

C_SOURCE = r"""
#include <math.h>
#include <float.h>
#include <stdint.h>
#include <string.h>
#include <stdlib.h>

/* computeRayKeys' set-up for the ray origin -> e: steps, tMax, tDelta (OctoMap's types); returns the
   float length |e - origin|. */
/* linear index of key k in the box whose low corner is lo */
static inline int64_t box_index(const int64_t *k, const int64_t *lo, const int64_t *strides)
{
    return (k[0] - lo[0]) * strides[0] + (k[1] - lo[1]) * strides[1] + (k[2] - lo[2]) * strides[2];
}

static inline float dda_setup(const float *origin, const float *e, const int64_t *key_origin, double res,
                              int64_t tree_max_val, int *step, double *tMax, double *tDelta)
{
    float d[3] = {e[0] - origin[0], e[1] - origin[1], e[2] - origin[2]};
    float nsq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    float length = (float) sqrt((double) nsq);
    d[0] /= length; d[1] /= length; d[2] /= length;
    for (int a = 0; a < 3; ++a) {
        if (d[a] > 0.0) step[a] = 1;
        else if (d[a] < 0.0) step[a] = -1;
        else step[a] = 0;
        if (step[a] != 0) {
            double border = ((double) ((int) key_origin[a] - (int) tree_max_val) + 0.5) * res;
            border += (float) (step[a] * res * 0.5);
            tMax[a] = (border - (double) origin[a]) / (double) d[a];
            tDelta[a] = res / fabs((double) d[a]);
        } else {
            tMax[a] = DBL_MAX;
            tDelta[a] = DBL_MAX;
        }
    }
    return length;
}

/* computeRayKeys(origin, end) for n ends. With mark == NULL: writes the linear indices to out
   (the origin cell first for every ray that leaves it) and returns their number, or -1 if cap is
   too small. With mark (a bitmap of mark_size bytes over the box, 0 = not seen): writes each index
   whose mark is 0 (setting it to 1), so out holds the distinct unmarked cells; -2 if an index falls
   outside. Cells pre-marked (e.g. 2 = occupied this frame) are skipped. The mark is set with an atomic
   exchange, so several threads may share one bitmap: each cell is written by exactly one of them. */
#define EMIT(x) do { if (mark) { if ((uint64_t) (x) >= (uint64_t) mark_size) return -2; \
        if (!mark[(x)] && !__atomic_exchange_n(mark + (x), (uint8_t) 1, __ATOMIC_RELAXED)) { \
            if (off >= cap) return -1; out[off++] = (x); } } \
        else { if (off >= cap) return -1; out[off++] = (x); } } while (0)
static inline int64_t ray_cells(const float *origin, const int64_t *key_origin, const float *ends,
                                const int64_t *key_ends, int64_t n, double res, const int64_t *lo,
                                const int64_t *strides, int64_t tree_max_val, int64_t *out, int64_t cap,
                                uint8_t *mark, int64_t mark_size)
{
    int64_t off = 0;
    const int64_t lin_o = box_index(key_origin, lo, strides);
    for (int64_t i = 0; i < n; ++i) {
        const float *e = ends + 3 * i;
        const int64_t *ke = key_ends + 3 * i;
        if (ke[0] == key_origin[0] && ke[1] == key_origin[1] && ke[2] == key_origin[2])
            continue;
        EMIT(lin_o);
        int step[3];
        double tMax[3], tDelta[3];
        const float length = dda_setup(origin, e, key_origin, res, tree_max_val, step, tMax, tDelta);
        /* the DDA step on scalars (the compiler keeps them in registers): the axis whose border is nearest */
        const int64_t lin_end = box_index(ke, lo, strides);
        const int64_t d0 = step[0] * strides[0], d1 = step[1] * strides[1], d2 = step[2] * strides[2];
        double t0 = tMax[0], t1 = tMax[1], t2 = tMax[2];
        const double dt0 = tDelta[0], dt1 = tDelta[1], dt2 = tDelta[2], len = (double) length;
        int64_t lin = lin_o;
        for (;;) {
            if (t0 < t1) {
                if (t0 < t2) { lin += d0; t0 += dt0; } else { lin += d2; t2 += dt2; }
            } else if (t1 < t2) { lin += d1; t1 += dt1; } else { lin += d2; t2 += dt2; }
            if (lin == lin_end) break;
            double dist = t0 < t1 ? t0 : t1;
            dist = dist < t2 ? dist : t2;
            if (dist > len) break;
            EMIT(lin);
        }
    }
    return off;
}

/* the two modes compiled separately (the mode test leaves the inner loop) */
int64_t mm_ray_cells(const float *origin, const int64_t *key_origin, const float *ends,
                     const int64_t *key_ends, int64_t n, double res, const int64_t *lo,
                     const int64_t *strides, int64_t tree_max_val, int64_t *out, int64_t cap,
                     uint8_t *mark, int64_t mark_size)
{
    if (mark)
        return ray_cells(origin, key_origin, ends, key_ends, n, res, lo, strides, tree_max_val, out, cap, mark,
                         mark_size);
    return ray_cells(origin, key_origin, ends, key_ends, n, res, lo, strides, tree_max_val, out, cap, NULL, 0);
}

/* Distribution-weighted rays (see mono_map/mapping/distribution.py). Ray i visits the cells of
   computeRayKeys(origin, end_i) and, if has_end[i], the end cell. A cell entered at ray length
   t_in and left at t_out (metres; the end cell is left at max(t_out, |end - origin|)) covers depths
   [t_in, t_out] * scale[i] of the ray's piecewise-uniform depth distribution (probs p[i*K..], edges
   e[i*edge_stride..], K bins, p_beyond[i] beyond them). Its expected OctoMap update is
   dl = P(in)*hit + P(beyond)*miss; updates smaller than min_update in magnitude are dropped. Per cell, the rays combine as: the largest positive dl if any,
   else the most negative one. With acc (a zeroed float bitmap over the box, 0 = untouched): each
   cell's index is written to out the first time, acc holds the combined dl; returns the count.
   With acc == NULL: (index, dl) pairs with repeats into out / out_dl. -1: cap too small; -2: outside. */
static inline double cdf_at(double z, const float *p, const double *e, int64_t K, int64_t *k, double *cum)
{
    while (*k < K && z >= e[*k + 1]) { *cum += (double) p[*k]; ++*k; }
    double c = *cum;
    if (*k < K) {
        double w = e[*k + 1] - e[*k];
        if (w > 0.0 && z > e[*k]) c += (double) p[*k] * (z - e[*k]) / w;
    }
    return c;
}

/* Far depth of one piecewise-uniform distribution: the depth where P(beyond) = mass - CDF + p_beyond
   first falls below eps (linear within the bin), else the last edge; mass: the sum of p in bin order. */
static inline double far_depth_mass(const float *p, double mass, double pb, const double *e, int64_t K, double eps)
{
    double beyond = mass + pb;                   /* P(beyond) at the lower edge of bin j */
    for (int64_t j = 0; j < K; ++j) {
        double after = beyond - (double) p[j];
        if (after < eps) {
            double f = p[j] > 0.0f ? (beyond - eps) / (double) p[j] : 0.0;
            f = f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
            return e[j] + (e[j + 1] - e[j]) * f;
        }
        beyond = after;
    }
    return e[K];
}

static inline double far_depth_one(const float *p, double pb, const double *e, int64_t K, double eps)
{
    double mass = 0.0;
    for (int64_t j = 0; j < K; ++j) mass += (double) p[j];
    return far_depth_mass(p, mass, pb, e, K, eps);
}

void mm_far_depth(const float *probs, const double *p_beyond, const double *edges, int64_t edge_stride,
                  int64_t K, int64_t n, double eps, double *out)
{
    for (int64_t i = 0; i < n; ++i)
        out[i] = far_depth_one(probs + K * i, p_beyond[i], edges + edge_stride * i, K, eps);
}

/* Rays' distributions in one pass (mono_map/mapping/distribution.py, ray_distributions): conditional bin
   probabilities q (n x K) at temperature T (inv_t = 1/T: q^(1/T) rescaled to the row's mass, rounded to
   float32, as apply_temperature), times (1 - p_beyond) (float32, as unconditional_mass) into out (n x K; may
   be q itself: element-wise), and each row's far depth (far_depth_one) into far. idx (n, or NULL): output row
   i reads q's row idx[i] (a gather without an intermediate copy). */
/* R rows of mm_ray_mass at once (R a constant where inlined: every per-row sum stays in bin order, and the
   R independent sums overlap in the pipeline instead of waiting for each other's additions) */
static inline __attribute__((always_inline)) void ray_mass_rows(const float *const *p, float *const *o, const double *pb, const double *const *e,
                                 int R, int64_t K, double inv_t, double eps, double *far)
{
    double keep[4], sp[4], sq[4], scale[4], mass[4];
    for (int r = 0; r < R; ++r) { keep[r] = 1.0 - pb[r]; sp[r] = 0.0; sq[r] = 0.0; mass[r] = 0.0; }
    if (inv_t == 1.0) {
        for (int64_t j = 0; j < K; ++j)
            for (int r = 0; r < R; ++r) {
                o[r][j] = (float) ((double) p[r][j] * keep[r]);
                mass[r] += (double) o[r][j];
            }
    } else {
        for (int64_t j = 0; j < K; ++j)
            for (int r = 0; r < R; ++r) {
                double x = (double) p[r][j];
                sp[r] += x;
                sq[r] += inv_t == 2.0 ? x * x : pow(x, inv_t);
            }
        for (int r = 0; r < R; ++r) scale[r] = sp[r] / (sq[r] > 0.0 ? sq[r] : 1.0);
        for (int64_t j = 0; j < K; ++j)             /* the tempered values again (a square: cheap) */
            for (int r = 0; r < R; ++r) {
                double x = (double) p[r][j];
                double t = inv_t == 2.0 ? x * x : pow(x, inv_t);
                o[r][j] = (float) ((double) (float) (t * scale[r]) * keep[r]);
                mass[r] += (double) o[r][j];
            }
    }
    /* far_depth_mass of the R rows, stepped together */
    double beyond[4];
    int done[4], left = R;
    for (int r = 0; r < R; ++r) { beyond[r] = mass[r] + pb[r]; done[r] = 0; }
    for (int64_t j = 0; j < K && left > 0; ++j)
        for (int r = 0; r < R; ++r) {
            if (done[r]) continue;
            const float *pr = o[r];
            double after = beyond[r] - (double) pr[j];
            if (after < eps) {
                double f = pr[j] > 0.0f ? (beyond[r] - eps) / (double) pr[j] : 0.0;
                f = f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
                far[r] = e[r][j] + (e[r][j + 1] - e[r][j]) * f;
                done[r] = 1;
                --left;
            } else beyond[r] = after;
        }
    for (int r = 0; r < R; ++r) if (!done[r]) far[r] = e[r][K];
}

void mm_ray_mass(const float *q, const double *p_beyond, int64_t n, int64_t K, double inv_t, const double *edges,
                 int64_t edge_stride, double eps, float *out, double *far, const int64_t *idx)
{
    int64_t i = 0;
    for (; i < n; i += 4) {
        const int R = n - i < 4 ? (int) (n - i) : 4;
        const float *p[4];
        float *o[4];
        const double *e[4];
        for (int r = 0; r < R; ++r) {
            p[r] = q + K * (idx ? idx[i + r] : i + r);
            o[r] = out + K * (i + r);
            e[r] = edges + edge_stride * (i + r);
        }
        if (R == 4) ray_mass_rows(p, o, p_beyond + i, e, 4, K, inv_t, eps, far + i);
        else for (int r = 0; r < R; ++r) ray_mass_rows(p + r, o + r, p_beyond + i + r, e + r, 1, K, inv_t, eps, far + i + r);
    }
}

/* Validation sums of n distributions (distribution.check_distribution): counts of non-finite and of negative
   values in probs (n x K) and p_beyond (n), their minima, and the largest row total sum(probs) + p_beyond.
   stats: [bad_p, neg_p, min_p, bad_b, neg_b, min_b, max_total]; counts over row totals above tol in *n_over.
   row_mass (n, or NULL): each row's sum of its finite probs in bin order (mm_ray_weights' per-ray mass). */
void mm_check_rows(const float *probs, const double *p_beyond, int64_t n, int64_t K, double tol, double *stats,
                   int64_t *n_over, double *row_mass)
{
    int64_t bad_p = 0, neg_p = 0, bad_b = 0, neg_b = 0, over = 0;
    double min_p = DBL_MAX, min_b = DBL_MAX, max_total = -DBL_MAX;
    for (int64_t i = 0; i < n; i += 4) {          /* 4 rows at a time, each row's total in bin order */
        const int R = n - i < 4 ? (int) (n - i) : 4;
        double total[4] = {0.0, 0.0, 0.0, 0.0};
        for (int64_t j = 0; j < K; ++j)
            for (int r = 0; r < R; ++r) {
                float x = probs[K * (i + r) + j];
                if (!isfinite(x)) { ++bad_p; continue; }
                if (x < 0.0f) { ++neg_p; }
                if ((double) x < min_p) min_p = (double) x;
                total[r] += (double) x;
            }
        for (int r = 0; r < R; ++r) {
            if (row_mass) row_mass[i + r] = total[r];
            double b = p_beyond[i + r];
            if (!isfinite(b)) ++bad_b;
            else {
                if (b < 0.0) ++neg_b;
                if (b < min_b) min_b = b;
                total[r] += b;
            }
            if (total[r] > max_total) max_total = total[r];
            if (total[r] > tol) ++over;
        }
    }
    stats[0] = (double) bad_p; stats[1] = (double) neg_p; stats[2] = min_p;
    stats[3] = (double) bad_b; stats[4] = (double) neg_b; stats[5] = min_b; stats[6] = max_total;
    *n_over = over;
}

/* The per-cell combination of several rays' updates v (each kept only if v != 0 and |v| >= min_update):
   the largest positive if any, else the most negative. */
#define COMBINE(best, v) do { float w_ = (v); if (w_ != 0.0f && fabsf(w_) >= min_update && \
        ((best) == 0.0f || (w_ > 0.0f ? ((best) < 0.0f || w_ > (best)) : ((best) < 0.0f && w_ < (best))))) \
        (best) = w_; } while (0)
#define COMBINE_ANY(best, w_) do { if ((best) == 0.0f || ((w_) > 0.0f ? ((best) < 0.0f || (w_) > (best)) : \
        ((best) < 0.0f && (w_) < (best)))) (best) = (w_); } while (0)          /* the same rule, no filter */
#define PUT(x, v) do { float v_ = (v); if (v_ != 0.0f) { if ((x) < 0 || (x) >= acc_size) { ret = -2; goto done; } \
        if (acc) { float o_ = acc[(x)]; \
            if (o_ == 0.0f) { if (off >= cap) { ret = -1; goto done; } acc[(x)] = v_; out[off++] = (x); } \
            else if (v_ > 0.0f ? (o_ < 0.0f || v_ > o_) : (o_ < 0.0f && v_ < o_)) acc[(x)] = v_; } \
        else { if (off >= cap) { ret = -1; goto done; } out_dl[off] = v_; out[off++] = (x); } } } while (0)
/* PUT(x, miss) for the most negative possible update (a whole miss: it replaces any negative, never a positive) */
#define PUT_MISS(x) do { if ((x) < 0 || (x) >= acc_size) { ret = -2; goto done; } \
        if (acc) { float o_ = acc[(x)]; \
            if (o_ == 0.0f) { if (off >= cap) { ret = -1; goto done; } acc[(x)] = miss; out[off++] = (x); } \
            else if (o_ < 0.0f && miss < o_) acc[(x)] = miss; } \
        else { if (off >= cap) { ret = -1; goto done; } out_dl[off] = miss; out[off++] = (x); } } while (0)
typedef struct { const float *p; const double *e; double sc, pb, mass, cum, c_in, c_out, z_sure; int64_t k; int sure; } RayState;
typedef struct { double t; int64_t j; } SortKey;
static int cmp_sort_key(const void *a, const void *b)
{
    double x = ((const SortKey *) a)->t, y = ((const SortKey *) b)->t;
    return x < y ? -1 : (x > y ? 1 : 0);
}
/* The depth below which a ray's update is surely <= thr (its free-space update then snaps to a whole miss;
   see mono_map/mapping/distribution.py, snap_threshold): every cell ending before it has
   dl <= c_out * hit + (mass + pb - c_out) * miss <= thr, i.e. CDF c_out <= C. Margins of 1e-9 (relative)
   cover the rounding of the CDF; -1 (never) when C < 0. */
static inline double sure_free_depth(const float *p, const double *e, int64_t K, double mass, double pb, double hit,
                                     double miss, double thr)
{
    double C = (thr - (mass + pb) * miss) / (hit - miss) - 1e-9, cum = 0.0;
    if (C < 0.0) return -1.0;
    for (int64_t b = 0; b < K; ++b) {
        double pb_ = (double) p[b];
        if (cum + pb_ > C) {
            double w = e[b + 1] - e[b];
            double z = (w > 0.0 && pb_ > 0.0) ? e[b] + (C - cum) / pb_ * w : e[b];
            return z * (1.0 - 1e-9);
        }
        cum += pb_;
    }
    return DBL_MAX;
}
/* Rays are walked in groups sharing one end cell (and so one end point, the cell's centre, and one DDA cell
   sequence): groups[g] .. groups[g + 1] - 1 index order[], which holds the rays' rows (ends, key_ends and
   has_end are read from the group's first ray). Each cell of the walk gets the combination of the group's
   rays' updates, so the walk and the memory traffic are paid once per group. */
int64_t mm_ray_weights(const float *origin, const int64_t *key_origin, const float *ends,
                       const int64_t *key_ends, const uint8_t *has_end, const double *scale,
                       const int64_t *order, const int64_t *groups, int64_t n_groups,
                       const float *probs, const double *p_beyond, const double *edges, int64_t edge_stride,
                       int64_t K, float hit, float miss, float min_update, double res, const int64_t *lo, const int64_t *strides,
                       int64_t tree_max_val, float *acc, int64_t acc_size, int64_t *out, float *out_dl,
                       int64_t cap, int snap, float thr, const double *ray_mass)
{
    int64_t off = 0, ret = 0, max_group = 0;
    for (int64_t g = 0; g < n_groups; ++g)
        if (groups[g + 1] - groups[g] > max_group) max_group = groups[g + 1] - groups[g];
    const size_t mg = (size_t) (max_group > 0 ? max_group : 1);
    RayState *st = (RayState *) malloc(sizeof(RayState) * mg);
    int64_t *act = (int64_t *) malloc(sizeof(int64_t) * mg);
    SortKey *sk = (SortKey *) malloc(sizeof(SortKey) * mg);
    if (!st || !act || !sk) { free(st); free(act); free(sk); return -3; }
    const int64_t lin_o = box_index(key_origin, lo, strides);
    const double dhit = (double) hit, dmiss = (double) miss;
    for (int64_t g = 0; g < n_groups; ++g) {
        const int64_t first = order[groups[g]], m = groups[g + 1] - groups[g];
        const float *e = ends + 3 * first;
        const int64_t *ke = key_ends + 3 * first;
        const int end_ok = has_end[first];
        for (int64_t j = 0; j < m; ++j) {
            const int64_t i = order[groups[g] + j];
            RayState *r = st + j;
            r->p = probs + K * i;
            r->e = edges + edge_stride * i;
            r->sc = scale[i];
            r->pb = p_beyond[i];
            double mass = 0.0;      /* the sum of its bins in bin order (given by the caller, or summed here) */
            if (ray_mass) mass = ray_mass[i];
            else for (int64_t b = 0; b < K; ++b) mass += (double) r->p[b];
            r->mass = mass;
            r->k = 0;
            r->cum = 0.0;
            r->c_in = cdf_at(0.0, r->p, r->e, K, &r->k, &r->cum);
            r->z_sure = snap ? sure_free_depth(r->p, r->e, K, mass, r->pb, dhit, dmiss, (double) thr) : -1.0;
            r->sure = r->z_sure > 0.0;
        }
        if (ke[0] == key_origin[0] && ke[1] == key_origin[1] && ke[2] == key_origin[2]) {
            /* empty rays: only the end cell, holding all the mass */
            if (end_ok) {
                float best = 0.0f;
                for (int64_t j = 0; j < m; ++j)
                    COMBINE(best, (float) ((st[j].mass - st[j].c_in) * dhit + st[j].pb * dmiss));
                PUT(lin_o, best);
            }
            continue;
        }
        int step[3];
        double tMax[3], tDelta[3];
        const float length = dda_setup(origin, e, key_origin, res, tree_max_val, step, tMax, tDelta);
        int64_t lin = lin_o;
        const int64_t lin_end = box_index(ke, lo, strides);
        /* the DDA step on scalars (the compiler keeps them in registers): the axis whose border is nearest */
        const int64_t d0 = step[0] * strides[0], d1 = step[1] * strides[1], d2 = step[2] * strides[2];
        double t0 = tMax[0], t1 = tMax[1], t2 = tMax[2];
        const double dt0 = tDelta[0], dt1 = tDelta[1], dt2 = tDelta[2], len = (double) length;
        double t_out = fmin(fmin(t0, t1), t2), t_in = 0.0;
        int64_t cell = lin_o;            /* the cell being left, entered with CDF c_in */
        /* rays in their sure-free zone wait in sk, by the ray length (metres) where the zone ends (shortened
           by 1e-12: t_out < sk.t implies t_out * sc < z_sure); the others are active, evaluated every cell */
        int64_t n_act = 0, n_sure = 0, s_head = 0;
        for (int64_t j = 0; j < m; ++j) {
            if (st[j].sure) {
                sk[n_sure].t = st[j].sc > 0.0 ? st[j].z_sure / st[j].sc * (1.0 - 1e-12) : DBL_MAX;
                sk[n_sure++].j = j;
            } else act[n_act++] = j;
        }
        if (n_sure > 1) qsort(sk, (size_t) n_sure, sizeof(SortKey), cmp_sort_key);
        for (;;) {
            if (t0 < t1) {
                if (t0 < t2) { lin += d0; t0 += dt0; } else { lin += d2; t2 += dt2; }
            } else if (t1 < t2) { lin += d1; t1 += dt1; } else { lin += d2; t2 += dt2; }
            int at_end = lin == lin_end;
            double dist = t0 < t1 ? t0 : t1;
            dist = dist < t2 ? dist : t2;
            int stop = at_end || dist > len;
            if (n_act == 0 && !stop && s_head < n_sure && t_out < sk[s_head].t) {
                /* every ray of the group still in its sure-free zone (most of a ray's length): the cell left
                   gets the whole miss that stands for them — the general step below would give the same */
                PUT_MISS(cell);
                t_in = t_out;
                t_out = dist;
                cell = lin;
                continue;
            }
            while (s_head < n_sure && (stop || t_out >= sk[s_head].t)) {   /* leaving its zone: exact from here */
                RayState *r = st + sk[s_head].j;
                r->sure = 0;
                r->c_in = cdf_at(t_in * r->sc, r->p, r->e, K, &r->k, &r->cum);   /* where the cell was entered */
                act[n_act++] = sk[s_head++].j;
            }
            /* the cell left now: free cell of the rays */
            float best = 0.0f;
            for (int64_t a = 0; a < n_act; ++a) {
                RayState *r = st + act[a];
                r->c_out = cdf_at(t_out * r->sc, r->p, r->e, K, &r->k, &r->cum);
                COMBINE(best, (float) ((r->c_out - r->c_in) * dhit + (r->mass - r->c_out + r->pb) * dmiss));
            }
            /* a whole miss stands for the waiting rays' updates (all <= thr <= -min_update: they pass the filter
               and snap to a miss; the stand-in is combined without the filter, as they would be) */
            if (s_head < n_sure) COMBINE_ANY(best, miss);
            PUT(cell, best);
            if (stop) {                  /* the end cell: from here to past the end point */
                if (end_ok) {
                    double t_end = dist > len ? dist : len;
                    if (!at_end) t_end = len > t_out ? len : t_out;
                    float best_end = 0.0f;
                    for (int64_t a = 0; a < n_act; ++a) {
                        RayState *r = st + act[a];
                        double c_end = cdf_at(t_end * r->sc, r->p, r->e, K, &r->k, &r->cum);
                        COMBINE(best_end, (float) ((c_end - r->c_out) * dhit + (r->mass - c_end + r->pb) * dmiss));
                    }
                    PUT(lin_end, best_end);
                }
                break;
            }
            int64_t kept = 0;
            for (int64_t a = 0; a < n_act; ++a) {
                RayState *r = st + act[a];
                if (r->mass - r->c_out + r->pb <= 0.0) continue;   /* no mass left from here on: the ray ends */
                r->c_in = r->c_out;
                act[kept++] = act[a];
            }
            n_act = kept;
            if (n_act == 0 && s_head == n_sure) break;
            t_in = t_out;
            t_out = dist;
            cell = lin;
        }
    }
    ret = off;
done:
    free(st);
    free(act);
    free(sk);
    return ret;
}

/* Merge accumulator b into a at b's n indices (mm_ray_weights' rule: the largest positive, else the most
   negative), zeroing b there; indices new to a are written to fresh (returns their count). */
int64_t mm_acc_merge(const int64_t *lin, int64_t n, float *a, float *b, int64_t *fresh)
{
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t x = lin[i];
        const float o = a[x], v = b[x];
        b[x] = 0.0f;
        if (o == 0.0f) { a[x] = v; fresh[m++] = x; }
        else if (v > 0.0f ? (o < 0.0f || v > o) : (o < 0.0f && v < o)) a[x] = v;
    }
    return m;
}

/* distribution.quantise_updates on n updates dl at indices lin (quantum > 0: rounded to multiples of quantum
   in float64, half to even as np.round, except values equal to hit or miss; snap: negatives become miss where
   <= miss / 2, else 0), the zeros dropped and the rest split by sign, each part in input order: the negatives
   to out_lin / out_dl[0 .. *n_neg), the positives after them; returns the number written. */
int64_t mm_quantise_split(const int64_t *lin, const float *dl, int64_t n, float hit, float miss, double quantum,
                          int snap, int64_t *out_lin, float *out_dl, int64_t *n_neg)
{
    int64_t neg = 0, pos = n;            /* negatives forward from the front, positives backward from the end */
    for (int64_t i = 0; i < n; ++i) {
        float v = dl[i];
        if (quantum > 0.0 && v != hit && v != miss)
            v = (float) (nearbyint((double) v / quantum) * quantum);
        if (snap && v < 0.0f) v = v <= miss / 2.0f ? miss : 0.0f;
        if (v == 0.0f) continue;
        int64_t at = v < 0.0f ? neg++ : --pos;
        out_lin[at] = lin[i];
        out_dl[at] = v;
    }
    /* the positives were written back to front: reverse them into input order, right after the negatives */
    for (int64_t a = pos, b = n - 1; a < b; ++a, --b) {
        int64_t tl = out_lin[a]; out_lin[a] = out_lin[b]; out_lin[b] = tl;
        float tv = out_dl[a]; out_dl[a] = out_dl[b]; out_dl[b] = tv;
    }
    if (pos > neg) {
        memmove(out_lin + neg, out_lin + pos, sizeof(int64_t) * (size_t) (n - pos));
        memmove(out_dl + neg, out_dl + pos, sizeof(float) * (size_t) (n - pos));
    }
    *n_neg = neg;
    return neg + (n - pos);
}

/* dl[i] = acc[lin[i]] for n indices, zeroing acc there (the buffer is left zeroed for the next frame). */
void mm_acc_take(const int64_t *lin, int64_t n, float *acc, float *dl)
{
    for (int64_t i = 0; i < n; ++i) { dl[i] = acc[lin[i]]; acc[lin[i]] = 0.0f; }
}

/* coordToKey for n float64 points (OctoMap: (int) floor(resolution_factor * (double)(float) p) + tree_max_val):
   float32 copies to pts32, keys to keys (n x 3), their inclusive bounds to lo / hi; returns the number of
   points whose key is outside [0, 2 * tree_max_val) (their keys are then meaningless). */
int64_t mm_point_keys(const double *pts, int64_t n, double rf, int64_t tree_max_val, float *pts32,
                      int64_t *keys, int64_t *lo, int64_t *hi)
{
    int64_t bad = 0;
    for (int a = 0; a < 3; ++a) { lo[a] = INT64_MAX; hi[a] = INT64_MIN; }
    for (int64_t i = 0; i < 3 * n; i += 3) {
        for (int a = 0; a < 3; ++a) {
            float f = (float) pts[i + a];
            pts32[i + a] = f;
            double c = rf * (double) f;    /* floor(c) in [-tmv, tmv) <=> c in [-tmv, tmv) */
            if (!(c >= (double) -tree_max_val && c < (double) tree_max_val)) { ++bad; keys[i + a] = 0; continue; }
            int64_t t = (int64_t) c;         /* floor without the libm call: truncate, then one down if above */
            int64_t k = t - ((double) t > c) + tree_max_val;
            keys[i + a] = k;
            if (k < lo[a]) lo[a] = k;
            if (k > hi[a]) hi[a] = k;
        }
    }
    return bad;
}

/* computeDiscreteUpdate's deduplication through the box bitmap: for each of n keys, the first one in its cell
   sets mark[cell] = 2 and writes its row to rows and, with centres, its cell centre (float) to centres;
   returns the count (-2: a key outside the box). */
int64_t mm_unique_cells(const int64_t *keys, int64_t n, const int64_t *lo, const int64_t *strides, uint8_t *mark,
                        int64_t mark_size, double res, int64_t tree_max_val, int64_t *rows, float *centres)
{
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t *k = keys + 3 * i;
        int64_t x = box_index(k, lo, strides);
        if (x < 0 || x >= mark_size) return -2;
        if (mark[x] == 2) continue;
        mark[x] = 2;
        rows[m] = i;
        if (centres)
            for (int a = 0; a < 3; ++a)
                centres[3 * m + a] = (float) (((double) (k[a] - tree_max_val) + 0.5) * res);
        ++m;
    }
    return m;
}

/* Exact floor division of 0 <= a < 2^50 by d > 0 through a double reciprocal (off by at most one, corrected):
   several times faster than the integer division. */
static inline int64_t div_fast(int64_t a, int64_t d, double inv)
{
    int64_t q = (int64_t) ((double) a * inv), r = a - q * d;
    if (r < 0) --q;
    else if (r >= d) ++q;
    return q;
}

/* Keys (n x 3) of linear box indices (KeyBox.keys). */
void mm_box_keys(const int64_t *lin, int64_t n, const int64_t *lo, const int64_t *strides, int64_t *keys)
{
    const int64_t s0 = strides[0], s1 = strides[1];
    const double i0 = 1.0 / (double) s0, i1 = 1.0 / (double) s1;
    for (int64_t i = 0; i < n; ++i) {
        int64_t a = div_fast(lin[i], s0, i0), r = lin[i] - a * s0;
        int64_t b = div_fast(r, s1, i1);
        keys[3 * i] = a + lo[0];
        keys[3 * i + 1] = b + lo[1];
        keys[3 * i + 2] = r - b * s1 + lo[2];
    }
}

/* The log-odds mirror (mono_map/mapping/integrate.py, LogOddsMirror): blocks of 8x8x8 cells, slot table[flat]
   (int32, -1 = none) over a dense box of blocks (low corner tlo, shape tsh); cell (x, y, z) of a block at
   pool[slot * 512 + (x & 7) * 64 + (y & 7) * 8 + (z & 7)]. */
static inline int64_t block_flat(const int64_t *k, const int64_t *tlo, const int64_t *tsh)
{
    int64_t b0 = (k[0] >> 3) - tlo[0], b1 = (k[1] >> 3) - tlo[1], b2 = (k[2] >> 3) - tlo[2];
    if (b0 < 0 || b0 >= tsh[0] || b1 < 0 || b1 >= tsh[1] || b2 < 0 || b2 >= tsh[2]) return -1;
    return (b0 * tsh[1] + b1) * tsh[2] + b2;
}

/* Give every block of the n keys a slot: missing blocks get slots n_blocks, n_blocks + 1, ... in order of first
   appearance, their flat table indices written to new_flat; returns how many (-2: a key outside the table). */
int64_t mm_mirror_alloc(const int64_t *keys, int64_t n, int32_t *table, const int64_t *tlo, const int64_t *tsh,
                        int64_t n_blocks, int64_t *new_flat)
{
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        int64_t f = block_flat(keys + 3 * i, tlo, tsh);
        if (f < 0) return -2;
        if (table[f] < 0) { table[f] = (int32_t) (n_blocks + m); new_flat[m++] = f; }
    }
    return m;
}

/* OctoMap's updateNode(key, log-odds update) for n distinct cells on the mirror (every block allocated): a cell
   already clamped in the update's direction is left alone (updateNode's early abort), otherwise
   new = clamp((known ? old : 0) + u) (float arithmetic), dirty[block slot] = 1. upd: per-key updates, or NULL for
   u_all. Rows whose occupied state (>= thres) flipped go to flip_rows (count in *n_flip). Returns the number of
   cells changed, -2 if a block is missing. */
int64_t mm_mirror_apply(const int64_t *keys, int64_t n, const float *upd, float u_all, const int32_t *table,
                        const int64_t *tlo, const int64_t *tsh, float *pool, uint8_t *dirty, float cmin,
                        float cmax, float thres, int64_t *flip_rows, int64_t *n_flip)
{
    int64_t changed = 0, nf = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t *k = keys + 3 * i;
        int64_t f = block_flat(k, tlo, tsh);
        if (f < 0 || table[f] < 0) return -2;
        int64_t x = (int64_t) table[f] * 512 + ((k[0] & 7) << 6) + ((k[1] & 7) << 3) + (k[2] & 7);
        float u = upd ? upd[i] : u_all;
        float old = pool[x];
        int known = !isnan(old);
        if (known && ((u >= 0.0f && old >= cmax) || (u <= 0.0f && old <= cmin))) continue;
        float v = (known ? old : 0.0f) + u;
        if (v < cmin) v = cmin;
        if (v > cmax) v = cmax;
        pool[x] = v;
        dirty[table[f]] = 1;
        ++changed;
        int was = known && old >= thres, is = v >= thres;
        if (was != is) flip_rows[nf++] = i;
    }
    *n_flip = nf;
    return changed;
}

/* OctoMap's .ot node stream (mono_map/mapping/octree.py: pre-order, per node float32 log-odds + child-mask
   byte; eight equal leaf children collapse into their parent, an inner node holds its children's maximum) of
   the mirror's known cells, straight from its 8x8x8 blocks: block b (pool + slot[b] * 512) at depth-13 code
   codes[b] (z, y, x bits interleaved), blocks sorted by code. With out == NULL the same walk only counts the
   nodes and leaves (the tree OctoMap would hold), and with a block cache (per block slot: dirty flag, kind,
   value, nodes, leaves) only the blocks marked dirty are walked, the others read from the cache. */
struct ot_ctx {
    uint8_t *out; int64_t pos, cap, leaves; int err; const float *pool; const int64_t *slot; const int64_t *codes;
    uint8_t *bdirty; int8_t *bkind; float *bval; int64_t *bnodes, *bleaves;
};

static inline void ot_put(struct ot_ctx *c, int64_t p, float v, uint8_t mask)
{
    if (!c->out) return;
    memcpy(c->out + 5 * p, &v, 4);
    c->out[5 * p + 4] = mask;
}

/* 0: no known cell below, 1: inner node, 2: leaf; *v: the node's value */
static int ot_child_sum(struct ot_ctx *c, int64_t p, const int *kind, const float *vals, float *v)
{
    uint8_t mask = 0;
    int nleaf = 0, any = 0;
    float vmax = 0.0f, vmin = 0.0f;
    for (int i = 0; i < 8; ++i) {
        if (!kind[i]) continue;
        mask |= (uint8_t) (1u << i);
        nleaf += kind[i] == 2;
        if (!any) { vmax = vmin = vals[i]; any = 1; }
        else { if (vals[i] > vmax) vmax = vals[i]; if (vals[i] < vmin) vmin = vals[i]; }
    }
    if (!mask) { c->pos = p; return 0; }
    *v = vmax;
    if (mask == 0xFF && nleaf == 8 && vmin == vmax) {   /* eight leaves become one */
        c->pos = p + 1; c->leaves -= 7; ot_put(c, p, vmax, 0); return 2;
    }
    ot_put(c, p, vmax, mask);
    return 1;
}

static int ot_cells(struct ot_ctx *c, const float *blk, int s, int x, int y, int z, float *v)
{
    if (s == 1) {
        float f = blk[(x << 6) | (y << 3) | z];
        if (isnan(f)) return 0;
        if (c->pos >= c->cap) { c->err = 1; return 0; }
        ot_put(c, c->pos++, f, 0);
        ++c->leaves;
        *v = f;
        return 2;
    }
    if (c->pos >= c->cap) { c->err = 1; return 0; }
    int64_t p = c->pos++;
    int h = s >> 1, kind[8];
    float vals[8];
    for (int i = 0; i < 8; ++i)
        kind[i] = ot_cells(c, blk, h, x + (i & 1) * h, y + ((i >> 1) & 1) * h, z + ((i >> 2) & 1) * h, vals + i);
    return ot_child_sum(c, p, kind, vals, v);
}

/* One block's subtree: walked, or read from the block cache when it has not changed since it was cached. */
static int ot_block(struct ot_ctx *c, int64_t b, float *v)
{
    int64_t s = c->slot[b];
    if (c->bkind && !c->bdirty[s]) {
        c->pos += c->bnodes[s];
        c->leaves += c->bleaves[s];
        *v = c->bval[s];
        return c->bkind[s];
    }
    int64_t p0 = c->pos, l0 = c->leaves;
    float w = 0.0f;
    int k = ot_cells(c, c->pool + s * 512, 8, 0, 0, 0, &w);
    *v = w;
    if (c->bkind) {
        c->bnodes[s] = c->pos - p0; c->bleaves[s] = c->leaves - l0;
        c->bkind[s] = (int8_t) k; c->bval[s] = w; c->bdirty[s] = 0;
    }
    return k;
}

static int ot_blocks(struct ot_ctx *c, int depth, int64_t a, int64_t b, float *v)
{
    if (depth == 13) return ot_block(c, a, v);
    if (c->pos >= c->cap) { c->err = 1; return 0; }
    int64_t p = c->pos++;
    int shift = 3 * (12 - depth), kind[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    float vals[8];
    for (int64_t i = a; i < b;) {
        int ci = (int) ((c->codes[i] >> shift) & 7);
        int64_t j = i + 1;
        while (j < b && (int) ((c->codes[j] >> shift) & 7) == ci) ++j;
        kind[ci] = ot_blocks(c, depth + 1, i, j, vals + ci);
        i = j;
    }
    return ot_child_sum(c, p, kind, vals, v);
}

/* Writes the stream's nodes (5 bytes each) to out (cap nodes; out == NULL: count only); returns their number,
   -1 if cap is too small; *leaves: the leaf count. bdirty ... bleaves: the block cache, or all NULL. */
int64_t mm_ot_nodes(const float *pool, const int64_t *slot, const int64_t *codes, int64_t n_blocks, uint8_t *out,
                    int64_t cap, int64_t *leaves, uint8_t *bdirty, int8_t *bkind, float *bval, int64_t *bnodes,
                    int64_t *bleaves)
{
    struct ot_ctx c = {out, 0, out ? cap : INT64_MAX, 0, 0, pool, slot, codes, bdirty, bkind, bval, bnodes, bleaves};
    float v;
    *leaves = 0;
    if (n_blocks == 0) return 0;
    ot_blocks(&c, 0, 0, n_blocks, &v);
    *leaves = c.leaves;
    return c.err ? -1 : c.pos;
}

/* Reads OctoMap's .ot node stream (pre-order; per node its float log-odds, then a byte whose bit i says
   child i exists): every leaf's min-corner key (x, y, z), depth (0 = root) and log-odds. Returns the leaf
   count; -1 if more than cap leaves, -2 if the stream ends inside a node, -3 if it is deeper than 16. */
struct otp { const uint8_t *d; int64_t n, pos, cap, m; int64_t *keys; int8_t *depth; float *val; int err; };

static void otp_node(struct otp *c, int level, int64_t kx, int64_t ky, int64_t kz)
{
    if (c->err) return;
    if (c->pos + 5 > c->n) { c->err = -2; return; }
    float v;
    memcpy(&v, c->d + c->pos, 4);
    uint8_t mask = c->d[c->pos + 4];
    c->pos += 5;
    if (mask == 0) {
        if (c->m >= c->cap) { c->err = -1; return; }
        c->keys[3 * c->m] = kx; c->keys[3 * c->m + 1] = ky; c->keys[3 * c->m + 2] = kz;
        c->depth[c->m] = (int8_t) level; c->val[c->m] = v; c->m++;
        return;
    }
    if (level >= 16) { c->err = -3; return; }
    int64_t bit = (int64_t) 1 << (15 - level);
    for (int i = 0; i < 8; ++i)
        if (mask & (1 << i))
            otp_node(c, level + 1, kx | ((i & 1) ? bit : 0), ky | ((i & 2) ? bit : 0), kz | ((i & 4) ? bit : 0));
}

int64_t mm_ot_leaves(const uint8_t *data, int64_t n, int64_t cap, int64_t *keys, int8_t *depth, float *val)
{
    struct otp c = {data, n, 0, cap, 0, keys, depth, val, 0};
    if (n > 0) otp_node(&c, 0, 0, 0, 0);
    return c.err ? c.err : c.m;
}
"""

_LIB = None
_TRIED = False

_P, _I64, _F32, _F64, _INT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_double, ctypes.c_int
# every exported function: (argtypes, restype)
_SIGNATURES = {
    "mm_ray_cells": ([_P, _P, _P, _P, _I64, _F64, _P, _P, _I64, _P, _I64, _P, _I64], _I64),
    "mm_ray_weights": ([_P, _P, _P, _P, _P, _P, _P, _P, _I64, _P, _P, _P, _I64, _I64, _F32, _F32, _F32, _F64, _P, _P,
                        _I64, _P, _I64, _P, _P, _I64, _INT, _F32, _P], _I64),
    "mm_far_depth": ([_P, _P, _P, _I64, _I64, _I64, _F64, _P], None),
    "mm_point_keys": ([_P, _I64, _F64, _I64, _P, _P, _P, _P], _I64),
    "mm_unique_cells": ([_P, _I64, _P, _P, _P, _I64, _F64, _I64, _P, _P], _I64),
    "mm_box_keys": ([_P, _I64, _P, _P, _P], None),
    "mm_mirror_alloc": ([_P, _I64, _P, _P, _P, _I64, _P], _I64),
    "mm_mirror_apply": ([_P, _I64, _P, _F32, _P, _P, _P, _P, _P, _F32, _F32, _F32, _P, _P], _I64),
    "mm_ot_nodes": ([_P, _P, _P, _I64, _P, _I64, _P, _P, _P, _P, _P, _P], _I64),
    "mm_ot_leaves": ([_P, _I64, _I64, _P, _P, _P], _I64),
    "mm_ray_mass": ([_P, _P, _I64, _I64, _F64, _P, _I64, _F64, _P, _P, _P], None),
    "mm_acc_merge": ([_P, _I64, _P, _P, _P], _I64),
    "mm_acc_take": ([_P, _I64, _P, _P], None),
    "mm_quantise_split": ([_P, _P, _I64, _F32, _F32, _F64, _INT, _P, _P, _P], _I64),
    "mm_check_rows": ([_P, _P, _I64, _I64, _F64, _P, _P, _P], None),
}


def load_kernel():
    """The compiled ``mm_ray_cells`` (ctypes function; the other kernels are its attributes without the
    ``mm_`` prefix, ``.weights`` is ``mm_ray_weights``) or None if unavailable/disabled (:mod:`mono_map.ckernel`)."""
    global _LIB, _TRIED
    if ckernel.disabled():
        return None
    if _TRIED:
        return _LIB
    _TRIED = True
    lib = ckernel.load("mm_dda", C_SOURCE, _SIGNATURES)
    if lib is None:
        return None
    fn = lib.mm_ray_cells
    fn.weights = lib.mm_ray_weights
    for name in _SIGNATURES:
        if name not in ("mm_ray_cells", "mm_ray_weights"):
            setattr(fn, name[3:], getattr(lib, name))
    _LIB = fn
    return _LIB


_PARALLEL_MIN_RAYS = 4096
_WEIGHT_CHUNKS = 16      # distribution rays: chunks of groups shared out between the two threads
_POOL = None


def _threads() -> int:
    """Threads for the kernel: ``$MONO_MAP_RAY_THREADS`` (1 or 2), else 2 when the process may use 2 CPUs."""
    env = os.environ.get("MONO_MAP_RAY_THREADS")
    if env:
        return max(1, min(2, int(env)))
    try:
        return min(2, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return min(2, os.cpu_count() or 1)


_POOL_LOCK = threading.Lock()


def _pool():
    global _POOL
    with _POOL_LOCK:   # builds in several threads share the one helper thread (each waits for its own half)
        if _POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mm-dda")
    return _POOL


def _capacity(ke: np.ndarray, ko: np.ndarray) -> int:
    """Cells the rays to key_ends ``ke`` can emit at most: their DDA steps plus slack."""
    return int(np.abs(ke - ko[None, :]).sum()) + 8 * len(ke) + 16


def _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out, mark=None) -> int:
    """One kernel call; returns the number of indices written to ``out`` (< 0: see the C source)."""
    return int(fn(o.ctypes.data, ko.ctypes.data, e.ctypes.data, ke.ctypes.data, len(e), float(resolution),
                  lo.ctypes.data, st.ctypes.data, int(tree_max_val), out.ctypes.data, len(out),
                  None if mark is None else mark.ctypes.data, 0 if mark is None else len(mark)))


def _distinct_cells(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, mark) -> np.ndarray:
    """The kernel with a bitmap: distinct linear indices of the rays o -> e, marked 1 in ``mark``."""
    out = np.empty(min(_capacity(ke, ko), len(mark)), dtype=np.int64)
    n = _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out, mark)
    if n < 0:   # -1 cannot happen (distinct cells <= min(steps, box)); -2: outside the box
        raise AssertionError("ray left its bounding box")  # the margin covers DDA overshoot
    return out[:n]


def ray_cells_c(fn, origin32: np.ndarray, key_origin: np.ndarray, ends32: np.ndarray, key_ends: np.ndarray,
                resolution: float, lo: np.ndarray, strides: np.ndarray, tree_max_val: int,
                mark: np.ndarray | None = None) -> np.ndarray | int:
    """Run the kernel; returns linear box indices (int64, with repeats), or with ``mark`` (uint8 bitmap
    over the box, 0 = unseen) the distinct indices of unmarked cells, marking them 1 in ``mark`` (cells
    already marked, e.g. 2 = occupied, are skipped). Large frames run on two threads sharing the bitmap
    (the kernel marks atomically, so each cell comes from one thread): same set of cells, see ``_threads``."""
    o = np.ascontiguousarray(origin32, dtype=np.float32)
    ko = np.ascontiguousarray(key_origin, dtype=np.int64)
    e = np.ascontiguousarray(ends32, dtype=np.float32)
    ke = np.ascontiguousarray(key_ends, dtype=np.int64)
    lo = np.ascontiguousarray(lo, dtype=np.int64)
    st = np.ascontiguousarray(strides, dtype=np.int64)
    if mark is not None:
        assert mark.dtype == np.uint8 and mark.flags.c_contiguous
        args = (o, ko, resolution, lo, st, tree_max_val)
        if len(e) < _PARALLEL_MIN_RAYS or _threads() < 2:
            return _distinct_cells(fn, *args, e, ke, mark)
        # two halves of equal DDA work on two threads (ctypes releases the GIL), deduplicating into
        # the one shared bitmap (consecutive rays, mostly neighbours, stay on one thread)
        steps = np.cumsum(np.abs(ke - ko[None, :]).sum(axis=1))
        cut = int(np.searchsorted(steps, steps[-1] / 2))
        future = _pool().submit(_distinct_cells, fn, *args, e[cut:], ke[cut:], mark)
        try:
            first = _distinct_cells(fn, *args, e[:cut], ke[:cut], mark)
            return np.concatenate([first, future.result()])
        except BaseException:            # e.g. Ctrl-C: the caller clears the bitmap once the other thread is done
            _settle(future)
            raise
    cap = _capacity(ke, ko)
    while True:
        out = np.empty(cap, dtype=np.int64)
        n = _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out)
        if n >= 0:
            return out[:n]
        cap *= 2


def ray_weights_c(fn, origin32: np.ndarray, key_origin: np.ndarray, ends32: np.ndarray, key_ends: np.ndarray,
                  has_end: np.ndarray, scale: np.ndarray, probs: np.ndarray, p_beyond: np.ndarray,
                  edges: np.ndarray, hit: float, miss: float, resolution: float, lo: np.ndarray,
                  strides: np.ndarray, tree_max_val: int, box_size: int, min_update: float = 0.0,
                  dense: bool = True, free_threshold: float | None = None, *,
                  ray_ids: np.ndarray, mass: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Run ``mm_ray_weights``: (linear box indices, float32 log-odds updates) of the distribution-weighted
    rays, one entry per distinct cell (rays combined: largest positive update, else most negative).
    Rays with the same ``ray_ids`` (int64 (N,)) share one walk, so they must
    have the same end point and ``has_end`` (in :func:`distribution_update`: the same far cell, whose centre
    and its cut at the range limit are the ray's end).
    dense=True accumulates in a float32 buffer over the whole box (reused across frames; on two threads
    for large frames, each half of the groups in its own buffer, merged by the same rule); dense=False writes
    (index, update) pairs with repeats and combines them here (for boxes too large to allocate).
    edges: (K+1,) for all rays or (N, K+1) per ray, float64 metres. ``free_threshold`` (a float32 update ≤
    −min_update; None: off): a cell where some ray's update is ≤ it and no ray's is positive may come out as
    exactly ``miss`` instead of the most negative update — for callers that snap such cells to a whole miss
    anyway (:func:`mono_map.mapping.distribution.snap_threshold`); the kernel then skips evaluating rays in
    the cells where their update is surely ≤ it (most of a ray's length). ``mass``: each ray's sum of its
    probs in bin order, float64 (N,), as :func:`check_rows_c` gives it (None: summed in the kernel)."""
    c = dict(o=np.ascontiguousarray(origin32, dtype=np.float32), ko=np.ascontiguousarray(key_origin, dtype=np.int64),
             lo=np.ascontiguousarray(lo, dtype=np.int64), st=np.ascontiguousarray(strides, dtype=np.int64),
             hit=float(hit), miss=float(miss), min_update=float(min_update), res=float(resolution),
             tmv=int(tree_max_val), box_size=int(box_size), snap=int(free_threshold is not None),
             thr=float(free_threshold) if free_threshold is not None else 0.0)
    rays = dict(e=np.ascontiguousarray(ends32, dtype=np.float32), ke=np.ascontiguousarray(key_ends, dtype=np.int64),
                he=np.ascontiguousarray(has_end, dtype=np.uint8), sc=np.ascontiguousarray(scale, dtype=np.float64),
                pr=np.ascontiguousarray(probs, dtype=np.float32), pb=np.ascontiguousarray(p_beyond, dtype=np.float64),
                ed=np.ascontiguousarray(edges, dtype=np.float64),
                ms=None if mass is None else np.ascontiguousarray(mass, dtype=np.float64))
    n = len(rays["e"])
    ids = np.asarray(ray_ids, dtype=np.int64)
    order = np.argsort(ids, kind="stable")
    srt = ids[order]
    groups = np.flatnonzero(np.r_[True, srt[1:] != srt[:-1]]) if n else np.zeros(0, np.int64)
    if not dense:
        lin, dl = _weights_run(fn, c, rays, order, groups, n, None)
        return combine_updates(lin, dl)
    if n < _PARALLEL_MIN_RAYS or _threads() < 2 or len(groups) < 2:
        acc = _zeroed_accumulator(0, box_size)
        try:
            lin, _ = _weights_run(fn, c, rays, order, groups, n, acc)
            return lin, _acc_take(fn, lin, acc)
        except BaseException:            # e.g. Ctrl-C: cells of unknown extent written; zero all for the next frame
            acc[:] = 0.0
            raise
    # the groups in chunks of about equal work (one DDA walk per group, each ray's set-up ~ 20 steps), taken by
    # two threads as they come free (each thread accumulates into its own buffer; merged below)
    sizes = np.diff(np.r_[groups, n])
    work = np.cumsum(np.abs(rays["ke"][order[groups]] - c["ko"][None, :]).sum(axis=1) + 20 * sizes)
    cuts = np.unique(np.r_[0, np.searchsorted(work, work[-1] * np.arange(1, _WEIGHT_CHUNKS) / _WEIGHT_CHUNKS),
                           len(groups)])
    chunks = iter(zip(cuts[:-1], cuts[1:]))
    lock, cancel = threading.Lock(), threading.Event()

    def worker(acc: np.ndarray) -> np.ndarray:
        lins = []
        while True:
            with lock:
                chunk = None if cancel.is_set() else next(chunks, None)
            if chunk is None:
                return np.concatenate(lins) if lins else np.zeros(0, np.int64)
            a, b = int(chunk[0]), int(chunk[1])
            lins.append(_weights_run(fn, c, rays, order, groups[a:b], int(groups[b]) if b < len(groups) else n,
                                     acc)[0])

    acc_a, acc_b = _zeroed_accumulator(0, box_size), _zeroed_accumulator(1, box_size)
    future = _pool().submit(worker, acc_b)
    try:
        lin_a = worker(acc_a)
        lin_b = future.result()
        fresh = np.empty(len(lin_b), dtype=np.int64)
        m = fn.acc_merge(lin_b.ctypes.data, len(lin_b), acc_a.ctypes.data, acc_b.ctypes.data, fresh.ctypes.data)
        lin = np.concatenate([lin_a, fresh[:m]])
        return lin, _acc_take(fn, lin, acc_a)
    except BaseException:                # e.g. Ctrl-C: stop the other thread, then zero both buffers for the next frame
        cancel.set()
        _settle(future)
        acc_a[:] = 0.0
        acc_b[:] = 0.0
        raise


def _settle(future) -> None:
    """Wait until the other thread's kernel call is over (its result or error is not wanted any more)."""
    import concurrent.futures

    concurrent.futures.wait([future])


def _acc_take(fn, lin: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """float32 acc[lin], zeroing those cells (the buffer stays zeroed for the next frame)."""
    lin = np.ascontiguousarray(lin, dtype=np.int64)
    dl = np.empty(len(lin), dtype=np.float32)
    fn.acc_take(lin.ctypes.data, len(lin), acc.ctypes.data, dl.ctypes.data)
    return dl


def _weights_run(fn, c: dict, r: dict, order: np.ndarray, starts: np.ndarray, stop: int,
                 acc: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """One ``mm_ray_weights`` call over the groups beginning at ``starts`` (positions in ``order``; the last
    ends at ``stop``): (distinct indices, None) accumulating into ``acc``, or with acc None the (index,
    update) pairs with repeats."""
    k = r["pr"].shape[1]
    edge_stride = 0 if r["ed"].ndim == 1 else r["ed"].shape[1]
    bounds = np.ascontiguousarray(np.r_[starts, stop], dtype=np.int64)
    cap = _capacity(r["ke"][order[starts]], c["ko"]) + 2 * len(starts)     # one walk (+ end cell) per group
    if acc is not None:
        cap = min(cap, c["box_size"])
    order = np.ascontiguousarray(order, dtype=np.int64)
    while True:
        out = np.empty(cap, dtype=np.int64)
        out_dl = None if acc is not None else np.empty(cap, dtype=np.float32)
        n = int(fn.weights(c["o"].ctypes.data, c["ko"].ctypes.data, r["e"].ctypes.data, r["ke"].ctypes.data,
                           r["he"].ctypes.data, r["sc"].ctypes.data, order.ctypes.data, bounds.ctypes.data,
                           len(starts), r["pr"].ctypes.data,
                           r["pb"].ctypes.data, r["ed"].ctypes.data, edge_stride, k, c["hit"], c["miss"],
                           c["min_update"], c["res"], c["lo"].ctypes.data, c["st"].ctypes.data, c["tmv"],
                           None if acc is None else acc.ctypes.data, c["box_size"], out.ctypes.data,
                           None if out_dl is None else out_dl.ctypes.data, len(out), c["snap"], c["thr"],
                           None if r["ms"] is None else r["ms"].ctypes.data))
        if n == -2:
            raise AssertionError("ray left its bounding box")  # the margin covers DDA overshoot
        if n == -3:
            raise MemoryError("mm_ray_weights: no memory for the ray states")
        if n >= 0:
            return out[:n], None if out_dl is None else out_dl[:n]
        if acc is not None:     # cannot happen (distinct cells <= box); guard against a partial write
            raise AssertionError("accumulator capacity exceeded")
        cap *= 2


_BUFFERS = threading.local()   # per calling thread: maps built in different threads never share a buffer


def _buffers():
    """This thread's per-frame buffers: the visited bitmap ``mark`` and the two accumulators ``acc``."""
    b = _BUFFERS
    if not hasattr(b, "mark"):
        b.mark = np.zeros(0, dtype=np.uint8)
        b.acc = [np.zeros(0, dtype=np.float32), np.zeros(0, dtype=np.float32)]
    return b


def _zeroed_accumulator(slot: int, size: int) -> np.ndarray:
    """Zeroed float32 buffer ``slot`` (one per kernel thread) of at least ``size`` cells, reused across
    frames (allocating and faulting in hundreds of MB per frame would cost more than the rays); callers zero
    what they touched."""
    acc = _buffers().acc
    if len(acc[slot]) < size:
        acc[slot] = np.zeros(max(size, int(len(acc[slot]) * 1.25)), dtype=np.float32)
    return acc[slot]


def combine_updates(lin: np.ndarray, dl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct index: the largest positive update if any, else the most negative (the kernel's rule)."""
    if len(lin) == 0:
        return lin, dl
    order = np.argsort(lin, kind="stable")
    lin, dl = lin[order], dl[order]
    starts = np.flatnonzero(np.r_[True, lin[1:] != lin[:-1]])
    hi = np.maximum.reduceat(dl, starts)
    low = np.minimum.reduceat(dl, starts)
    return lin[starts], np.where(hi > 0, hi, low).astype(np.float32)


def quantise_split_c(fn, lin: np.ndarray, dl: np.ndarray, hit: float, miss: float, quantum: float,
                     snap_free: bool) -> tuple[np.ndarray, np.ndarray, int]:
    """``mm_quantise_split``: the updates ``dl`` (float32) at indices ``lin`` (int64) rounded as
    :func:`mono_map.mapping.distribution.quantise_updates`, the zeros dropped, the negatives first, then the
    positives (each in input order): (indices, updates, number of negatives)."""
    lin = np.ascontiguousarray(lin, dtype=np.int64)
    dl = np.ascontiguousarray(dl, dtype=np.float32)
    out_lin, out_dl = np.empty(len(lin), dtype=np.int64), np.empty(len(lin), dtype=np.float32)
    n_neg = np.zeros(1, dtype=np.int64)
    m = fn.quantise_split(lin.ctypes.data, dl.ctypes.data, len(lin), float(hit), float(miss), float(quantum),
                          int(bool(snap_free)), out_lin.ctypes.data, out_dl.ctypes.data, n_neg.ctypes.data)
    return out_lin[:m], out_dl[:m], int(n_neg[0])


def far_depth_c(fn, probs: np.ndarray, p_beyond: np.ndarray, edges: np.ndarray, eps: float) -> np.ndarray:
    """``mm_far_depth``: (N,) float64 depth where P(beyond) first falls below eps (see distribution.far_depth)."""
    pr = np.ascontiguousarray(probs, dtype=np.float32)
    pb = np.ascontiguousarray(p_beyond, dtype=np.float64)
    ed = np.ascontiguousarray(edges, dtype=np.float64)
    out = np.empty(len(pr), dtype=np.float64)
    fn.far_depth(pr.ctypes.data, pb.ctypes.data, ed.ctypes.data, 0 if ed.ndim == 1 else ed.shape[1], pr.shape[1],
                 len(pr), float(eps), out.ctypes.data)
    return out


def ray_mass_c(fn, probs: np.ndarray, p_beyond: np.ndarray, inv_temperature: float, edges: np.ndarray,
               eps: float, overwrite: bool = False, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``mm_ray_mass``: (float32 (N, K) unconditional bin mass, float64 (N,) far depths) of conditional bin
    probabilities (N, K) at temperature 1 / inv_temperature (see distribution.ray_distributions);
    ``overwrite``: the mass is written over ``probs`` when it is a C-contiguous float32 array; ``rows``
    (int64 (N,)): the rays are these rows of ``probs`` (M, K) (read in place, no gathered copy; not with
    overwrite); p_beyond and per-ray edges are then per ray."""
    pr = np.ascontiguousarray(probs, dtype=np.float32)
    pb = np.ascontiguousarray(p_beyond, dtype=np.float64)
    ed = np.ascontiguousarray(edges, dtype=np.float64)
    idx = None if rows is None else np.ascontiguousarray(rows, dtype=np.int64)
    k = pr.shape[1]
    n = len(pr) if idx is None else len(idx)
    if idx is not None and n and (idx.min() < 0 or idx.max() >= len(pr)):
        raise IndexError("ray_mass_c: row index out of range")
    if len(pb) != n or (ed.ndim == 2 and len(ed) != n):
        raise ValueError(f"ray_mass_c: {n} rays but {len(pb)} p_beyond values / edges of shape {ed.shape}")
    out = pr if overwrite and idx is None else np.empty((n, k), dtype=np.float32)   # element-wise: in place is safe
    far = np.empty(n, dtype=np.float64)
    es = 0 if ed.ndim == 1 else ed.shape[1]

    def part(a: int, b: int) -> None:      # rays a..b-1 (row by row: halves on two threads give the same bits)
        src, ix = (pr.ctypes.data + 4 * k * a, None) if idx is None else (pr.ctypes.data, idx.ctypes.data + 8 * a)
        fn.ray_mass(src, pb.ctypes.data + 8 * a, b - a, k, float(inv_temperature), ed.ctypes.data + 8 * es * a, es,
                    float(eps), out.ctypes.data + 4 * k * a, far.ctypes.data + 8 * a, ix)

    _on_two_threads(part, n)
    return out, far


def _on_two_threads(rows, n: int) -> None:
    """rows(a, b) over 0..n: in two halves on two threads for large n (ctypes releases the GIL), else at once."""
    if n < _PARALLEL_MIN_RAYS or _threads() < 2:
        rows(0, n)
        return
    half = n // 2
    future = _pool().submit(rows, half, n)
    rows(0, half)
    future.result()


def check_rows_c(fn, probs: np.ndarray, p_beyond: np.ndarray, tol: float, mass: np.ndarray | None = None) -> dict:
    """``mm_check_rows``: counts and extremes of N distributions' values (see distribution.check_distribution);
    ``mass`` (float64 (N,), C-contiguous): filled with each row's sum of finite probs in bin order."""
    assert mass is None or (mass.dtype == np.float64 and mass.flags.c_contiguous and mass.shape == (len(probs),))
    pr = np.ascontiguousarray(probs, dtype=np.float32)
    pb = np.ascontiguousarray(p_beyond, dtype=np.float64)
    k = pr.shape[1] if pr.ndim == 2 else 0
    # rows on two threads, each half its own stats; a half not run keeps the neutral ones
    stats = np.array([[0, 0, np.inf, 0, 0, np.inf, -np.inf]] * 2, dtype=np.float64)
    over = np.zeros(2, dtype=np.int64)

    def rows(a: int, b: int) -> None:
        h = int(a > 0)
        fn.check_rows(pr.ctypes.data + 4 * k * a, pb.ctypes.data + 8 * a, b - a, k, float(tol),
                      stats[h].ctypes.data, over[h:].ctypes.data, None if mass is None else mass.ctypes.data + 8 * a)

    _on_two_threads(rows, len(pr))
    keys = ("bad_p", "neg_p", "min_p", "bad_b", "neg_b", "min_b", "max_total")
    tot, low, high = stats.sum(axis=0), stats.min(axis=0), stats.max(axis=0)    # counts, minima, the max total
    vals = [tot[0], tot[1], low[2], tot[3], tot[4], low[5], high[6]]
    return dict(zip(keys, (float(v) for v in vals)), n_over=int(over.sum()))


def point_keys_c(fn, points: np.ndarray, resolution: float, tree_max_val: int):
    """``mm_point_keys``: (float32 points (N, 3), int64 keys (N, 3), key lo (3,), key hi (3,), #points out of range)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    n = len(pts)
    pts32 = np.empty((n, 3), dtype=np.float32)
    keys = np.empty((n, 3), dtype=np.int64)
    lo, hi = np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64)
    bad = fn.point_keys(pts.ctypes.data, n, 1.0 / float(resolution), int(tree_max_val), pts32.ctypes.data,
                        keys.ctypes.data, lo.ctypes.data, hi.ctypes.data)
    return pts32, keys, lo, hi, int(bad)


def unique_cells_c(fn, keys: np.ndarray, lo: np.ndarray, strides: np.ndarray, mark: np.ndarray,
                   resolution: float, tree_max_val: int, centres: bool = True):
    """``mm_unique_cells``: (rows of the first key in each cell, float32 cell centres of those rows or None);
    marks those cells 2 in ``mark``."""
    k = np.ascontiguousarray(keys, dtype=np.int64)
    rows = np.empty(len(k), dtype=np.int64)
    cen = np.empty((len(k), 3), dtype=np.float32) if centres else None
    m = fn.unique_cells(k.ctypes.data, len(k), np.ascontiguousarray(lo, dtype=np.int64).ctypes.data,
                        np.ascontiguousarray(strides, dtype=np.int64).ctypes.data, mark.ctypes.data, len(mark),
                        float(resolution), int(tree_max_val), rows.ctypes.data, None if cen is None else cen.ctypes.data)
    if m < 0:
        raise AssertionError("key outside its bounding box")   # the box is built from these keys
    return rows[:m], None if cen is None else cen[:m]


def box_keys_c(fn, lin: np.ndarray, lo: np.ndarray, strides: np.ndarray) -> np.ndarray:
    """``mm_box_keys``: (N, 3) int64 keys of linear box indices."""
    lin = np.ascontiguousarray(lin, dtype=np.int64)
    out = np.empty((len(lin), 3), dtype=np.int64)
    fn.box_keys(lin.ctypes.data, len(lin), np.ascontiguousarray(lo, dtype=np.int64).ctypes.data,
                np.ascontiguousarray(strides, dtype=np.int64).ctypes.data, out.ctypes.data)
    return out


def mirror_alloc_c(fn, keys: np.ndarray, table: np.ndarray, table_lo: np.ndarray, n_blocks: int) -> np.ndarray:
    """``mm_mirror_alloc``: flat table indices of the blocks of ``keys`` that had no slot (now slots
    n_blocks, n_blocks + 1, ... in that order)."""
    assert table.dtype == np.int32 and table.flags.c_contiguous
    shape = np.array(table.shape, dtype=np.int64)
    out = np.empty(min(len(keys), table.size), dtype=np.int64)
    m = fn.mirror_alloc(keys.ctypes.data, len(keys), table.ctypes.data,
                        np.ascontiguousarray(table_lo, dtype=np.int64).ctypes.data, shape.ctypes.data, int(n_blocks),
                        out.ctypes.data)
    if m < 0:
        raise AssertionError("key outside the mirror's block table")   # the caller grows the table first
    return out[:m]


def mirror_apply_c(fn, keys: np.ndarray, update, table: np.ndarray, table_lo: np.ndarray, pool: np.ndarray,
                   dirty: np.ndarray, cmin, cmax, thres) -> tuple[int, np.ndarray]:
    """``mm_mirror_apply``: OctoMap's clamped update of distinct cells ``keys`` by ``update`` (float32 scalar or
    (N,) array); returns (#cells changed, rows of ``keys`` whose occupied state flipped). Large frames run
    on two threads, each on half of the keys (distinct cells: no two threads write one cell)."""
    assert pool.dtype == np.float32 and dirty.dtype == np.bool_ and table.dtype == np.int32
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    upd = None if np.ndim(update) == 0 else np.ascontiguousarray(update, dtype=np.float32)
    shape = np.array(table.shape, dtype=np.int64)
    tlo = np.ascontiguousarray(table_lo, dtype=np.int64)

    def run(a: int, b: int) -> tuple[int, np.ndarray]:
        flips = np.empty(b - a, dtype=np.int64)
        n_flip = np.zeros(1, dtype=np.int64)
        n = fn.mirror_apply(keys[a:b].ctypes.data, b - a, None if upd is None else upd[a:b].ctypes.data,
                            float(update) if upd is None else 0.0, table.ctypes.data, tlo.ctypes.data,
                            shape.ctypes.data, pool.ctypes.data, dirty.ctypes.data, float(cmin), float(cmax),
                            float(thres), flips.ctypes.data, n_flip.ctypes.data)
        if n < 0:
            raise AssertionError("mirror block missing")   # mirror_alloc_c runs first
        return int(n), flips[:int(n_flip[0])] + a

    if len(keys) < _PARALLEL_MIN_RAYS or _threads() < 2:
        return run(0, len(keys))
    cut = len(keys) // 2
    future = _pool().submit(run, cut, len(keys))
    n_a, f_a = run(0, cut)
    n_b, f_b = future.result()
    return n_a + n_b, np.concatenate([f_a, f_b])


def release_buffers() -> None:
    """Free this thread's per-frame buffers kept between frames (visited bitmap, accumulators): at the end
    of a build."""
    vars(_BUFFERS).clear()   # the next _buffers() call starts this thread's buffers empty


def zeroed_bitmap(size: int) -> np.ndarray:
    """A zeroed uint8 bitmap of ``size`` cells, this thread's, reused across frames (as the accumulators);
    the caller zeroes the cells it marked before the next frame."""
    b = _buffers()
    if len(b.mark) < size:
        b.mark = np.zeros(max(size, int(len(b.mark) * 1.25)), dtype=np.uint8)
    return b.mark[:size]


def _blocks_in_code_order(block_codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(block slots sorted by their depth-13 code, the sorted codes), as ``mm_ot_nodes`` walks them."""
    codes = np.asarray(block_codes, dtype=np.int64)
    slot = np.argsort(codes, kind="stable").astype(np.int64)
    return slot, np.ascontiguousarray(codes[slot])


def ot_nodes_c(fn, pool: np.ndarray, block_codes: np.ndarray, header: bytes = b"") -> tuple[np.ndarray, int]:
    """``mm_ot_nodes``: (``header`` + the node bytes of OctoMap's .ot stream as a uint8 array, node count) of the
    known (non-NaN) cells of a log-odds mirror: float32 ``pool`` of blocks of 8×8×8 cells (see
    integrate.LogOddsMirror), ``block_codes`` (B,) each block's depth-13 code
    (``octree.child_order_codes(block_key >> 3)``). The nodes are the same bytes as ``octree.ot_stream`` of
    those cells. The buffer is sized for the worst case but only the written pages take memory."""
    assert pool.dtype == np.float32 and pool.flags.c_contiguous
    slot, codes = _blocks_in_code_order(block_codes)
    cap = (512 + 64 + 8 + 1 + 13) * len(slot) + 1     # a full block's subtree and its path to the root
    h = len(header)
    out = np.empty(h + 5 * cap, dtype=np.uint8)
    out[:h] = np.frombuffer(header, dtype=np.uint8)
    leaves = np.zeros(1, dtype=np.int64)
    n = fn.ot_nodes(pool.ctypes.data, slot.ctypes.data, codes.ctypes.data, len(slot), out[h:].ctypes.data, cap,
                    leaves.ctypes.data, None, None, None, None, None)
    if n < 0:
        raise AssertionError("node bound exceeded")   # cannot happen: cap bounds every block's nodes
    return out[:h + 5 * n], int(n)


def ot_counts_c(fn, pool: np.ndarray, block_codes: np.ndarray, cache: dict | None = None) -> tuple[int, int]:
    """``mm_ot_nodes`` counting only: (nodes, leaves) of the octree the mirror's known cells make (OctoMap's
    ``size()`` and ``getNumLeafNodes()``). ``cache``: per block slot arrays ``dirty`` (bool), ``kind`` (int8),
    ``value`` (float32), ``nodes`` and ``leaves`` (int64): only dirty blocks are walked; they are cached and
    marked clean."""
    slot, codes = _blocks_in_code_order(block_codes)
    leaves = np.zeros(1, dtype=np.int64)
    if cache is None:
        ptrs = (None,) * 5
    else:
        arrays = (cache["dirty"], cache["kind"], cache["value"], cache["nodes"], cache["leaves"])
        for a, dt in zip(arrays, (np.bool_, np.int8, np.float32, np.int64, np.int64)):
            assert a.dtype == dt and a.flags.c_contiguous and len(a) >= len(slot)
        ptrs = tuple(a.ctypes.data for a in arrays)
    n = fn.ot_nodes(pool.ctypes.data, slot.ctypes.data, codes.ctypes.data, len(slot), None, 0, leaves.ctypes.data,
                    *ptrs)
    return int(n), int(leaves[0])


def ot_leaves_c(fn, data: np.ndarray, n_leaves: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mm_ot_leaves``: (min-corner keys (N, 3) int64, depths (N,) int64, float32 log-odds (N,)) of the
    leaves of a .ot node stream (uint8, header stripped) holding ``n_leaves`` leaves."""
    d = np.ascontiguousarray(data, dtype=np.uint8)
    keys = np.empty((n_leaves, 3), dtype=np.int64)
    depth = np.empty(n_leaves, dtype=np.int8)
    val = np.empty(n_leaves, dtype=np.float32)
    m = fn.ot_leaves(d.ctypes.data, len(d), n_leaves, keys.ctypes.data, depth.ctypes.data, val.ctypes.data)
    if m < 0 or m != n_leaves:
        raise AssertionError(f"mm_ot_leaves: {m} (tree of {n_leaves} leaves)")   # OctoMap wrote the stream
    return keys, depth.astype(np.int64), val
