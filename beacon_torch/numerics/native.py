"""Loop kernels in C, for the recurrences that tensor operations cannot batch away.

The cavities' published transport sweep updates the cells in place one after the other,
each reading the new values of its west and south neighbours. As tensor operations it
is a chain of ``nx + ny - 1`` dependent anti-diagonal steps per substep, whose fixed
cost per operation (a few microseconds) is most of a cavity step at small batches. The
same loop written in C, over the cells with the members innermost, costs what its
arithmetic costs.

The pressure increment's solve has a recurrence of the same kind: once the field is in
the eigenbasis of the x operator, each x mode is a tridiagonal system along y, whose
elimination (forward, then back) is a chain of ``ny`` dependent steps. In C it costs a
few operations a cell, against the ``ny`` multiply-adds a cell of the dense y
eigenvector products it replaces.

The kernel is compiled from the source below with the system's C compiler, once per
process, into a fresh private directory (nothing is read from a shared cache, so no
file that someone else could have written is ever loaded), and called through
``ctypes`` on the tensors' memory. Where there is no compiler, the build fails, the
tensors are not on the CPU, or ``BEACON_TORCH_NATIVE=0``, :func:`applies` says no and
the caller keeps its tensor path.

Both kernels are differentiable: each is an operator of torch's dispatcher with its
adjoint written beside it. The sweep's adjoint is the reverse sweep (a C kernel of the
same loop run backwards), the tridiagonal solve's is the same solve (its matrix is symmetric, or
similar to its transpose through the cells' widths), so that a gradient through a
cavity step keeps the fast loops instead of a graph of thousands of small operations.
The staggered grid's explicit momentum terms keep their tensor form forwards (inductor
fuses it well); their adjoint is a C loop in which each velocity takes back what the
terms that read it send (autograd's backward of their slices is a zero padding each,
read under masks).

Under ``torch.func.vmap`` the mapped dimension joins the members (the loops treat every
member alike), and a compiled graph calls them as any other operator.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
import threading
import warnings

import torch

# Written as the published loop: x outer, y inner, each cell's new value
# (c + a * west) + b * south, members innermost (the contiguous axis, so the compiler
# vectorises it). No fused multiply-adds, so that the float64 results are the
# published ones to the last bits that plain arithmetic allows.
_SOURCE = r"""
/* The adjoint loops carry gradients that decay as they travel upstream, below the
   smallest normal number, where each operation on them costs tens of times a normal
   one (measured: the TVD adjoint 24 times slower on such rows). Inside those loops,
   and only there, such numbers are taken as zero (the x86 flags flush-to-zero and
   denormals-are-zero, restored on return): a change below 1.2e-38 (float32) or 2.2e-308
   (float64) in a gradient. */
#if defined(__SSE__) || defined(__x86_64__)
#include <xmmintrin.h>
#define FLUSH_BEGIN unsigned int saved_csr = _mm_getcsr(); _mm_setcsr(saved_csr | 0x8040u);
#define FLUSH_END _mm_setcsr(saved_csr);
#else
#define FLUSH_BEGIN
#define FLUSH_END
#endif
/* A loop whose arrays the compiler cannot tell apart (pointers into one work buffer)
   but which reads no element another iteration writes: vectorise it without the
   run-time overlap checks it would otherwise give up on. */
#if defined(__clang__)
#define IVDEP _Pragma("clang loop vectorize(assume_safety)")
#elif defined(__GNUC__)
#define IVDEP _Pragma("GCC ivdep")
#else
#define IVDEP
#endif
/* The 1-D adjoints read an action's stored states backwards, a substep's row (a few
   kilobytes) at a time, from memory the forward loop left long before: streams too
   short and too far apart for the hardware's prefetcher. While substep k of row b runs,
   the row the next iteration reads (substep k - 1, or the next row's last) is fetched
   into the cache; nothing computed changes. */
#if defined(__GNUC__)
#define PREFETCH_NEXT_STATE(T, WIDTH)                                               \
    {                                                                               \
        const T *next_ = k > 0 ? states + (b * substeps + k - 1) * (WIDTH)          \
                               : (b + 1 < rows ? states + ((b + 2) * substeps - 1) * (WIDTH) : states); \
        for (long j_ = 0; j_ < (WIDTH); j_ += 64 / (long)sizeof(T)) __builtin_prefetch(next_ + j_); \
    }
#else
#define PREFETCH_NEXT_STATE(T, WIDTH)
#endif
/* The 2-D flows' kernels loop over a cell's members innermost, a count known only when
   called, and the compiler's vector loop is then wider than a row of 8 float32 members:
   such a row ran through the remainder's code. Where a kernel measured faster so, it is
   inlined for the actor-critic's batches (8 members, and 16 where that paid too), the
   count a constant and the row whole vectors; the results are the same to the last bit
   (2026-12-07: the sweep and the line solve 1.8 times faster at 8 float32 members, the
   momentum adjoint 2.5 times; the line solve at 16 and the reverse sweep were slower,
   and are not). */
#if defined(__GNUC__) || defined(__clang__)
#define INLINED static inline __attribute__((always_inline))
#else
#define INLINED static inline
#endif

#define SWEEP(NAME, T)                                                              \
INLINED void NAME##_rows(                                                           \
          T *out, const T *s, const T *a, const T *b, long nx, long ny, long members) { \
    const long column = (ny + 2) * members;                                         \
    for (long m = 0; m < column; ++m) {  /* the ghosts keep their values */         \
        out[m] = s[m];                                                              \
        out[(nx + 1) * column + m] = s[(nx + 1) * column + m];                      \
    }                                                                               \
    for (long i = 1; i <= nx; ++i) {                                                \
        T *o = out + i * column;                                                    \
        const T *si = s + i * column;                                               \
        for (long m = 0; m < members; ++m) {                                        \
            o[m] = si[m];                                                           \
            o[(ny + 1) * members + m] = si[(ny + 1) * members + m];                 \
        }                                                                           \
        for (long j = 1; j <= ny; ++j) {                                            \
            T *x = o + j * members;                                                 \
            const T *old = si + j * members, *west = x - column, *south = x - members; \
            const T *ai = a + ((i - 1) * ny + (j - 1)) * members;                   \
            const T *bi = b + ((i - 1) * ny + (j - 1)) * members;                   \
            for (long m = 0; m < members; ++m)                                      \
                x[m] = (old[m] + ai[m] * west[m]) + bi[m] * south[m];               \
        }                                                                           \
    }                                                                               \
}                                                                                   \
void NAME(T *out, const T *s, const T *a, const T *b, long nx, long ny, long members) { \
    if (members == 8) NAME##_rows(out, s, a, b, nx, ny, 8);                         \
    else if (members == 16) NAME##_rows(out, s, a, b, nx, ny, 16);                  \
    else NAME##_rows(out, s, a, b, nx, ny, members);                                \
}
SWEEP(sweep_f32, float)
SWEEP(sweep_f64, double)

/* Tridiagonal systems along the second axis of f [modes, n, members], one per mode,
   solved from their precomputed elimination into out: row j of mode k is
   x[j] = (y[j] - upper[j] x[j + 1]) inv[k, j] after y[j] = f[j] - lower[k, j] y[j - 1]
   (a singular mode has inv 0 on its last row, which leaves that value at 0). */
#define LINES(NAME, T)                                                              \
INLINED void NAME##_rows(                                                           \
          T *out, const T *f, const T *lower, const T *inv, const T *upper,         \
          long modes, long n, long members) {                                       \
    for (long k = 0; k < modes; ++k) {                                              \
        T *x = out + k * n * members;                                               \
        const T *r = f + k * n * members, *l = lower + k * n, *w = inv + k * n;     \
        for (long m = 0; m < members; ++m) x[m] = r[m];                             \
        for (long j = 1; j < n; ++j) {                                              \
            T *row = x + j * members, *prev = row - members;                        \
            const T *rj = r + j * members;                                          \
            for (long m = 0; m < members; ++m) row[m] = rj[m] - l[j] * prev[m];     \
        }                                                                           \
        for (long m = 0; m < members; ++m) x[(n - 1) * members + m] *= w[n - 1];   \
        for (long j = n - 2; j >= 0; --j) {                                         \
            T *row = x + j * members, *next = row + members;                        \
            for (long m = 0; m < members; ++m)                                      \
                row[m] = (row[m] - upper[j] * next[m]) * w[j];                      \
        }                                                                           \
    }                                                                               \
}                                                                                   \
void NAME(T *out, const T *f, const T *lower, const T *inv, const T *upper,         \
          long modes, long n, long members) {                                       \
    if (members == 8) NAME##_rows(out, f, lower, inv, upper, modes, n, 8);          \
    else NAME##_rows(out, f, lower, inv, upper, modes, n, members);                 \
}
LINES(lines_f32, float)
LINES(lines_f64, double)

/* The adjoint of SWEEP: given the gradient g of its output x (both ghosted), the
   gradient lam of x's own values, accumulated in the reverse of the sweep's order
   (each cell's lam is final once the cells that read it, east and north, are done:
   lam[i, j] = g[i, j] + a[i + 1, j] lam[i + 1, j] + b[i, j + 1] lam[i, j + 1]), is the
   gradient of s; the west and south ghosts collect what the first column and row read
   of them. The coefficients' gradients are lam times the neighbour each one weighed. */
#define SWEEP_ADJOINT(NAME, T)                                                      \
void NAME(T *lam, T *ga, T *gb, const T *g, const T *x, const T *a, const T *b,     \
          long nx, long ny, long members) {                                         \
    FLUSH_BEGIN                                                                     \
    const long column = (ny + 2) * members;                                         \
    for (long m = 0; m < (nx + 2) * column; ++m) lam[m] = g[m];                     \
    for (long i = nx; i >= 1; --i) {                                                \
        for (long j = ny; j >= 1; --j) {                                            \
            T *l = lam + i * column + j * members;                                  \
            if (i < nx) {                                                           \
                const T *east = l + column, *ae = a + (i * ny + (j - 1)) * members; \
                for (long m = 0; m < members; ++m) l[m] += ae[m] * east[m];         \
            }                                                                       \
            if (j < ny) {                                                           \
                const T *north = l + members, *bn = b + ((i - 1) * ny + j) * members; \
                for (long m = 0; m < members; ++m) l[m] += bn[m] * north[m];        \
            }                                                                       \
        }                                                                           \
    }                                                                               \
    for (long j = 1; j <= ny; ++j) {  /* the west ghosts, read by the first column */ \
        T *l = lam + j * members;                                                   \
        const T *first = l + column, *a1 = a + (j - 1) * members;                   \
        for (long m = 0; m < members; ++m) l[m] += a1[m] * first[m];                \
    }                                                                               \
    for (long i = 1; i <= nx; ++i) {  /* the south ghosts, read by the first row */ \
        T *l = lam + i * column;                                                    \
        const T *first = l + members, *b1 = b + (i - 1) * ny * members;             \
        for (long m = 0; m < members; ++m) l[m] += b1[m] * first[m];                \
    }                                                                               \
    for (long i = 1; i <= nx; ++i) {                                                \
        for (long j = 1; j <= ny; ++j) {                                            \
            const T *l = lam + i * column + j * members;                            \
            const T *west = x + (i - 1) * column + j * members, *south = x + i * column + (j - 1) * members; \
            T *gai = ga + ((i - 1) * ny + (j - 1)) * members, *gbi = gb + ((i - 1) * ny + (j - 1)) * members; \
            for (long m = 0; m < members; ++m) {                                    \
                gai[m] = l[m] * west[m];                                            \
                gbi[m] = l[m] * south[m];                                           \
            }                                                                       \
        }                                                                           \
    }                                                                               \
    FLUSH_END                                                                       \
}
SWEEP_ADJOINT(sweep_adjoint_f32, float)
SWEEP_ADJOINT(sweep_adjoint_f64, double)

/* The adjoint of the TVD derivative D_i = (F_{i+1/2} - F_{i-1/2}) / dx of each row of f
   [rows, n] (faces F_j = f_j + phi(r_j) d_j / 2, d_j = f_{j+1} - f_j,
   r_j = d_{j-1} / (d_j + 1e-8), phi_0 = 0): from the gradient g [rows, n - 2] of D, the
   gradient of f, in the forward's own stencil form. Per row: each face's gradient G_j;
   then what each face hands the differences it read (A_j to d_j, W_j to d_{j-1}, the
   limiter's slope included: van Leer's, or minmod's, 1 on [0, 1] as clamp's backward);
   then each cell's share of the differences next to it. work holds 2 n values. */
#define TVD_FACES(T, SLOPE)                                                         \
        for (long j = 1; j <= n - 2; ++j) {                                         \
            T G = o[j], dj = fr[j + 1] - fr[j], dm = fr[j] - fr[j - 1];             \
            T inv = (T)1 / (dj + (T)1e-8), r = dm * inv, phi, slope;                \
            SLOPE(T)                                                                \
            T w = (T)0.5 * G * dj * slope * inv;                                    \
            A[j] = (T)0.5 * G * phi - w * r;                                        \
            W[j] = w;                                                               \
        }
#define MINMOD_SLOPE(T)                                                             \
            phi = r < 0 ? (T)0 : (r > 1 ? (T)1 : r);                                \
            slope = (r >= 0 && r <= 1) ? (T)1 : (T)0;
#define VAN_LEER_SLOPE(T)                                                           \
            T a = r < 0 ? -r : r, s = (T)(r > 0) - (T)(r < 0), iq = (T)1 / (1 + a); \
            phi = (r + a) * iq;                                                     \
            slope = ((1 + s) - phi * s) * iq;
/* (the limiter is chosen outside the loop over faces, and no array aliases another,
   so that the compiler vectorises that loop: a third of the time of the scalar one; each
   face divides twice, by its difference and by van Leer's 1 + |r|, and multiplies by
   the reciprocals, which changes the gradient by round-off only) */
#define TVD_ADJOINT(NAME, T)                                                        \
void NAME(T *restrict out, T *restrict work, const T *restrict f, const T *restrict g, \
          long rows, long n, T dx, long minmod) {                                   \
    FLUSH_BEGIN                                                                     \
    T *restrict A = work, *restrict W = work + n, idx = (T)1 / dx;                 \
    for (long b = 0; b < rows; ++b) {                                               \
        const T *restrict fr = f + b * n, *restrict gr = g + b * (n - 2);           \
        T *restrict o = out + b * n;                                                \
        o[0] = -(gr[0] * idx);                                                      \
        for (long j = 1; j <= n - 3; ++j) o[j] = gr[j - 1] * idx - gr[j] * idx;     \
        o[n - 2] = gr[n - 3] * idx;                                                 \
        A[0] = 0; W[0] = 0; A[n - 1] = 0; W[n - 1] = 0;                             \
        if (minmod) { TVD_FACES(T, MINMOD_SLOPE) } else { TVD_FACES(T, VAN_LEER_SLOPE) } \
        for (long k = 0; k <= n - 2; ++k) A[k] = A[k] + W[k + 1];                   \
        o[n - 1] = A[n - 2];                                                        \
        for (long k = n - 2; k >= 1; --k) o[k] = (o[k] - A[k]) + A[k - 1];          \
        o[0] = o[0] - A[0];                                                         \
    }                                                                               \
    FLUSH_END                                                                       \
}
TVD_ADJOINT(tvd_adjoint_f32, float)
TVD_ADJOINT(tvd_adjoint_f64, double)

/* Whole actions of the 1-D flows, one row (member) at a time, every substep of that row
   while it sits in the cache; their adjoints run the substeps of a row in reverse from
   the states the action stored (its fields at the start of each substep). Each forward
   operation, and its order, is the tensor loop's, so that a row comes out bit for bit as
   that loop leaves it; the adjoints are autograd's gradient of that loop to round-off.
   The row macros below read the row length n, the cell width dx (idx = 1 / dx) and the
   work rows d, faces (forward) and o, A, W (adjoint). */
#define VAN_LEER_PHI(T) T a = r < 0 ? -r : r, phi = (r + a) / ((T)1 + a);
#define MINMOD_PHI(T) T phi = r < 0 ? (T)0 : (r > 1 ? (T)1 : r);
/* D[i] (i < n - 2): the TVD derivative of the row X at the interior cells */
#define TVD_DERIVATIVE(T, PHI, X, D)                                                \
    {                                                                               \
        const T *restrict x_ = (X);                                                 \
        for (long j = 0; j < n - 1; ++j) d[j] = x_[j + 1] - x_[j];                  \
        faces[0] = x_[0] + ((T)0.5 * (T)0) * d[0];                                  \
        for (long j = 1; j <= n - 2; ++j) {                                         \
            T r = d[j - 1] / (d[j] + (T)1e-8);                                      \
            PHI(T)                                                                  \
            faces[j] = x_[j] + ((T)0.5 * phi) * d[j];                               \
        }                                                                           \
        for (long i = 0; i < n - 2; ++i) (D)[i] = (faces[i + 1] - faces[i]) / dx;   \
    }
/* OUT (n) += the gradient of the row X of its TVD derivative's gradient GD (n - 2),
   as TVD_ADJOINT computes it */
#define TVD_ADJOINT_ADD(T, SLOPE, X, GD, OUT)                                       \
    {                                                                               \
        const T *restrict fr = (X), *restrict gd_ = (GD);                           \
        o[0] = -(gd_[0] * idx);                                                     \
        for (long j = 1; j <= n - 3; ++j) o[j] = gd_[j - 1] * idx - gd_[j] * idx;   \
        o[n - 2] = gd_[n - 3] * idx;                                                \
        A[0] = 0; W[0] = 0; A[n - 1] = 0; W[n - 1] = 0;                             \
        TVD_FACES(T, SLOPE)                                                         \
        for (long j = 0; j <= n - 2; ++j) A[j] = A[j] + W[j + 1];                   \
        (OUT)[n - 1] += A[n - 2];                                                   \
        for (long j = n - 2; j >= 1; --j) (OUT)[j] += (o[j] - A[j]) + A[j - 1];     \
        (OUT)[0] += o[0] - A[0];                                                    \
    }

/* burgers-v0: u_i <- ((4 u_i - p_i) + c ((-u_i) D_i - s_i)) / 3 at the interior cells
   (D the TVD derivative of u, van Leer; p: u one substep before; c = 2 dt; s the held
   forcing), the inlet value at the first cell, the last interior value at the outlet.
   states [rows, substeps, n]; work 3 n values. */
#define BURGERS_ACTION(NAME, T)                                                     \
void NAME(T *restrict u_out, T *restrict p_out, T *restrict states, T *restrict work, \
          const T *restrict u0, const T *restrict p0, const T *restrict inlet,      \
          const T *restrict s, long rows, long n, long substeps, T dx, T c) {       \
    T *restrict d = work, *restrict faces = work + n, *restrict D = work + 2 * n;  \
    for (long b = 0; b < rows; ++b) {                                               \
        const T *restrict sb = s + b * (n - 2), *restrict prev = p0 + b * n;        \
        T *restrict first = states + b * substeps * n;                              \
        for (long j = 0; j < n; ++j) first[j] = u0[b * n + j];                      \
        for (long k = 0; k < substeps; ++k) {                                       \
            const T *restrict x = states + (b * substeps + k) * n;                  \
            T *restrict next = k + 1 < substeps ? states + (b * substeps + k + 1) * n : u_out + b * n; \
            TVD_DERIVATIVE(T, VAN_LEER_PHI, x, D)                                   \
            for (long i = 0; i < n - 2; ++i) {                                      \
                T f = (-x[i + 1]) * D[i] - sb[i];                                   \
                next[i + 1] = (((T)4 * x[i + 1] - prev[i + 1]) + c * f) / (T)3;     \
            }                                                                       \
            next[0] = inlet[b];                                                     \
            next[n - 1] = next[n - 2];                                              \
            prev = x;                                                               \
        }                                                                           \
        for (long j = 0; j < n; ++j) p_out[b * n + j] = prev[j];                    \
    }                                                                               \
}
BURGERS_ACTION(burgers_action_f32, float)
BURGERS_ACTION(burgers_action_f64, double)

/* Its adjoint: from the gradients gu, gp of the action's new (u, p), those of its
   (u, p), of the inlet value and of the forcing. Per substep, with t = g_interior / 3
   (the outlet's share added to the last interior cell's): the forcing collects -c t,
   u_i collects 4 t - c t D_i, the TVD derivative the gradient gD_i = -c t u_i, p_i -t,
   and u's gradient the previous p's. Three loops a substep, each vectorised: t and
   gD; the faces (the limiter once, with its slope, two divisions a face, the face
   values for D and what each face hands the differences it read, A to its own, W to
   the one before); the cells (D, and the shares of the differences next to each).
   gD sits one place in, between zeros, so that every face reads it alike. work 6 n
   values. */
#define BURGERS_ADJOINT(NAME, T)                                                    \
void NAME(T *restrict gu_out, T *restrict gp_out, T *restrict g_inlet, T *restrict g_s, \
          T *restrict work, const T *restrict states, const T *restrict gu,         \
          const T *restrict gp, long rows, long n, long substeps, T dx, T c) {      \
    FLUSH_BEGIN                                                                     \
    T *restrict gD = work, *restrict faces = work + n, *restrict A = work + 2 * n;  \
    T *restrict W = work + 3 * n, *restrict G = work + 4 * n, *restrict t = work + 5 * n; \
    T idx = (T)1 / dx, third = (T)1 / (T)3;                                         \
    gD[0] = 0; gD[n - 1] = 0; A[0] = 0; W[0] = 0; W[n - 1] = 0;                     \
    for (long b = 0; b < rows; ++b) {                                               \
        T *restrict Gu = gu_out + b * n, *restrict Gp = gp_out + b * n, *restrict gs = g_s + b * (n - 2); \
        T inlet_sum = 0;                                                            \
        for (long j = 0; j < n; ++j) { Gu[j] = gu[b * n + j]; Gp[j] = gp[b * n + j]; } \
        for (long i = 0; i < n - 2; ++i) gs[i] = 0;                                 \
        for (long k = substeps - 1; k >= 0; --k) {                                  \
            const T *restrict x = states + (b * substeps + k) * n;                  \
            PREFETCH_NEXT_STATE(T, n)                                               \
            inlet_sum += Gu[0];                                                     \
            Gu[n - 2] += Gu[n - 1];                                                 \
            for (long i = 0; i < n - 2; ++i) {                                      \
                T ti = Gu[i + 1] * third, gf = c * ti;                              \
                t[i] = ti;                                                          \
                gs[i] -= gf;                                                        \
                gD[i + 1] = gf * (-x[i + 1]);                                       \
            }                                                                       \
            for (long j = 1; j <= n - 2; ++j) {                                     \
                T dj = x[j + 1] - x[j], dm = x[j] - x[j - 1];                       \
                T inv = (T)1 / (dj + (T)1e-8), r = dm * inv, phi, slope;            \
                VAN_LEER_SLOPE(T)                                                   \
                T Gj = (gD[j] - gD[j + 1]) * idx, w = (T)0.5 * Gj * dj * slope * inv; \
                faces[j] = x[j] + ((T)0.5 * phi) * dj;                              \
                G[j] = Gj;                                                          \
                A[j] = (T)0.5 * Gj * phi - w * r;                                   \
                W[j] = w;                                                           \
            }                                                                       \
            faces[0] = x[0];                                                        \
            T first = Gp[0] - gD[1] * idx - W[1], last = Gp[n - 1] + A[n - 2];      \
            for (long j = 1; j <= n - 2; ++j) {                                     \
                T ti = t[j - 1], D = (faces[j] - faces[j - 1]) * idx;               \
                Gu[j] = Gp[j] + ((T)4 * ti - (c * ti) * D) + G[j] - (A[j] + W[j + 1]) + (A[j - 1] + W[j]); \
                Gp[j] = -ti;                                                        \
            }                                                                       \
            Gu[0] = first; Gu[n - 1] = last;                                        \
            Gp[0] = 0; Gp[n - 1] = 0;                                               \
        }                                                                           \
        g_inlet[b] = inlet_sum;                                                     \
    }                                                                               \
    FLUSH_END                                                                       \
}
BURGERS_ADJOINT(burgers_adjoint_f32, float)
BURGERS_ADJOINT(burgers_adjoint_f64, double)

/* shkadov-v0: per substep k, with the forcing F = fp + alpha_k (fn - fp) and S = 5 delta
   (a row's own), Dq and Df the TVD derivatives (minmod) of q and of the flux
   q q / (h + G), t3 the third derivative of h (the one-sided stencil, the backward one at
   the last two interior cells):
     dh = -Dq,  dq = (-1.2 Df + (h (t3 + 1) - q / (h h + G)) / S) - F,
     h <- h + c (3 dh - dh_prev),  q <- q + c (3 dq - dq_prev)  (c = dt / 2)
   at the interior cells, h = inlet_k and q = 1 at the first cell, the last interior
   values at the outlet. states [rows, substeps, 2, n] (h, q); work 6 n values. */
#define SHKADOV_FLUX_AND_THIRD(T)                                                   \
            for (long j = 0; j < n; ++j) flux[j] = (xq[j] * xq[j]) / (xh[j] + (T)1e-8); \
            for (long i = 0; i < n - 4; ++i)                                        \
                t3[i] = ((((-xh[i + 4]) + (T)6 * xh[i + 3]) - (T)12 * xh[i + 2]) + (T)10 * xh[i + 1] \
                         - (T)3 * xh[i]) / third_a;                                 \
            for (long i = n - 4; i < n - 2; ++i)                                    \
                t3[i] = (((xh[i + 1] - (T)3 * xh[i]) + (T)3 * xh[i - 1]) - xh[i - 2]) / third_b;
#define SHKADOV_ACTION(NAME, T)                                                     \
void NAME(T *restrict h_out, T *restrict q_out, T *restrict dh_out, T *restrict dq_out, \
          T *restrict states, T *restrict work, const T *restrict h0, const T *restrict q0, \
          const T *restrict dh0, const T *restrict dq0, const T *restrict fp,       \
          const T *restrict fn, const T *restrict alpha, const T *restrict inlet,   \
          const T *restrict scale, long rows, long n, long substeps, T dx, T c,     \
          T third_a, T third_b) {                                                   \
    T *restrict d = work, *restrict faces = work + n, *restrict flux = work + 2 * n; \
    T *restrict Dq = work + 3 * n, *restrict Df = work + 4 * n, *restrict t3 = work + 5 * n; \
    for (long b = 0; b < rows; ++b) {                                               \
        const T *restrict fpb = fp + b * (n - 2), *restrict fnb = fn + b * (n - 2); \
        T *restrict dhp = dh_out + b * (n - 2), *restrict dqp = dq_out + b * (n - 2); \
        T *restrict first = states + b * substeps * 2 * n, S = scale[b];           \
        for (long j = 0; j < n; ++j) { first[j] = h0[b * n + j]; first[n + j] = q0[b * n + j]; } \
        for (long i = 0; i < n - 2; ++i) { dhp[i] = dh0[b * (n - 2) + i]; dqp[i] = dq0[b * (n - 2) + i]; } \
        for (long k = 0; k < substeps; ++k) {                                       \
            const T *restrict xh = states + (b * substeps + k) * 2 * n, *restrict xq = xh + n; \
            T *restrict nh = k + 1 < substeps ? states + (b * substeps + k + 1) * 2 * n : h_out + b * n; \
            T *restrict nq = k + 1 < substeps ? nh + n : q_out + b * n;            \
            T al = alpha[k];                                                        \
            SHKADOV_FLUX_AND_THIRD(T)                                               \
            TVD_DERIVATIVE(T, MINMOD_PHI, xq, Dq)                                   \
            TVD_DERIVATIVE(T, MINMOD_PHI, flux, Df)                                 \
            for (long i = 0; i < n - 2; ++i) {                                      \
                T hi = xh[i + 1], qi = xq[i + 1];                                   \
                T dh = -Dq[i];                                                      \
                T rest = (hi * (t3[i] + (T)1) - qi / (hi * hi + (T)1e-8)) / S;      \
                T dq = ((T)-1.2 * Df[i] + rest) - (fpb[i] + al * (fnb[i] - fpb[i])); \
                nh[i + 1] = hi + c * ((T)3 * dh - dhp[i]);                          \
                nq[i + 1] = qi + c * ((T)3 * dq - dqp[i]);                          \
                dhp[i] = dh;                                                        \
                dqp[i] = dq;                                                        \
            }                                                                       \
            nh[0] = inlet[k * rows + b]; nq[0] = (T)1;                              \
            nh[n - 1] = nh[n - 2]; nq[n - 1] = nq[n - 2];                           \
        }                                                                           \
    }                                                                               \
}
SHKADOV_ACTION(shkadov_action_f32, float)
SHKADOV_ACTION(shkadov_action_f64, double)

/* Its adjoint: from the gradients of the action's new (h, q, dh, dq), those of its
   (h, q, dh_prev, dq_prev), of the two forcings, of each substep's inlet value
   (g_inlet [substeps, rows]) and of each row's S. The flux is the forward's own (its
   division), so that the limiter takes the forward's branches; elsewhere the loops
   multiply by reciprocals, and S's gradient sums its terms after the loop that fills
   them, which then vectorises. work 14 n + 8 values. */
#define SHKADOV_ADJOINT(NAME, T)                                                    \
void NAME(T *restrict gh_out, T *restrict gq_out, T *restrict gdh_out, T *restrict gdq_out, \
          T *restrict g_fp, T *restrict g_fn, T *restrict g_inlet, T *restrict g_scale, \
          T *restrict work, const T *restrict states, const T *restrict alpha,      \
          const T *restrict scale, const T *restrict gh, const T *restrict gq,      \
          const T *restrict gdh, const T *restrict gdq, long rows, long n, long substeps, \
          T dx, T c, T third_a, T third_b) {                                        \
    FLUSH_BEGIN                                                                     \
    T *restrict flux = work + 2 * n;                                                \
    T *restrict Dq = work + 3 * n, *restrict Df = work + 4 * n, *restrict t3 = work + 5 * n; \
    T *restrict o = work + 6 * n, *restrict A = work + 7 * n, *restrict W = work + 8 * n; \
    T *restrict Nh = work + 9 * n, *restrict Nq = work + 10 * n, *restrict gflux = work + 11 * n; \
    T *restrict terms = work + 12 * n, *restrict e = work + 13 * n, *restrict inv_h = work; \
    T idx = (T)1 / dx, ita = (T)1 / third_a, itb = (T)1 / third_b;                 \
    for (long j = 0; j < n + 8; ++j) e[j] = 0;                                      \
    for (long b = 0; b < rows; ++b) {                                               \
        T *restrict Gh = gh_out + b * n, *restrict Gq = gq_out + b * n;             \
        T *restrict Gdh = gdh_out + b * (n - 2), *restrict Gdq = gdq_out + b * (n - 2); \
        T *restrict gfp = g_fp + b * (n - 2), *restrict gfn = g_fn + b * (n - 2);   \
        T S = scale[b], iS = (T)1 / S, gS = 0;                                      \
        for (long j = 0; j < n; ++j) { Gh[j] = gh[b * n + j]; Gq[j] = gq[b * n + j]; } \
        for (long i = 0; i < n - 2; ++i) {                                          \
            Gdh[i] = gdh[b * (n - 2) + i]; Gdq[i] = gdq[b * (n - 2) + i];           \
            gfp[i] = 0; gfn[i] = 0;                                                 \
        }                                                                           \
        for (long k = substeps - 1; k >= 0; --k) {                                  \
            const T *restrict xh = states + (b * substeps + k) * 2 * n, *restrict xq = xh + n; \
            PREFETCH_NEXT_STATE(T, 2 * n)                                           \
            T al = alpha[k];                                                        \
            g_inlet[k * rows + b] = Gh[0];                                          \
            Gh[n - 2] += Gh[n - 1];                                                 \
            Gq[n - 2] += Gq[n - 1];                                                 \
            /* the flux as the forward's, for the limiter's branches */            \
            IVDEP for (long j = 0; j < n; ++j) {                                    \
                T den = xh[j] + (T)1e-8;                                            \
                flux[j] = (xq[j] * xq[j]) / den;                                    \
                inv_h[j] = (T)1 / den;                                              \
            }                                                                       \
            for (long i = 0; i < n - 4; ++i)                                        \
                t3[i] = ((((-xh[i + 4]) + (T)6 * xh[i + 3]) - (T)12 * xh[i + 2]) + (T)10 * xh[i + 1] \
                         - (T)3 * xh[i]) * ita;                                     \
            for (long i = n - 4; i < n - 2; ++i)                                    \
                t3[i] = (((xh[i + 1] - (T)3 * xh[i]) + (T)3 * xh[i - 1]) - xh[i - 2]) * itb; \
            for (long j = 0; j < n; ++j) { Nh[j] = 0; Nq[j] = 0; gflux[j] = 0; }    \
            IVDEP for (long i = 0; i < n - 2; ++i) {                                \
                T hi = xh[i + 1], qi = xq[i + 1], sh = c * Gh[i + 1], sq = c * Gq[i + 1]; \
                T gdh_ = Gdh[i] + (T)3 * sh, gdq_ = Gdq[i] + (T)3 * sq;             \
                T gF = -gdq_, iden = (T)1 / (hi * hi + (T)1e-8), gN = gdq_ * iS;    \
                T rest = (hi * (t3[i] + (T)1) - qi * iden) * iS;                    \
                gfp[i] += gF - al * gF;                                             \
                gfn[i] += al * gF;                                                  \
                terms[i] = gdq_ * rest * iS;                                        \
                Nh[i + 1] = Gh[i + 1] + gN * (t3[i] + (T)1) + gN * qi * ((T)2 * hi) * (iden * iden); \
                Nq[i + 1] = Gq[i + 1] - gN * iden;                                  \
                e[i + 4] = gN * hi;  /* the third derivative's gradient */          \
                Dq[i] = -gdh_;  /* now the gradient of Dq */                        \
                Df[i] = (T)-1.2 * gdq_;  /* and of Df */                            \
                Gdh[i] = -sh;                                                       \
                Gdq[i] = -sq;                                                       \
            }                                                                       \
            for (long i = 0; i < n - 2; ++i) gS -= terms[i];                        \
            /* the third derivative's stencils, transposed: e[i + 4] weighs cell i's, and */ \
            /* the one-sided stencil's weights stop at cell n - 5 (zeros around them) */ \
            T last = e[n], next_to_last = e[n + 1];                                 \
            e[n] = 0; e[n + 1] = 0;                                                 \
            IVDEP for (long m = 0; m < n; ++m)                                      \
                Nh[m] += ((-e[m] + (T)6 * e[m + 1]) - (T)12 * e[m + 2] + (T)10 * e[m + 3] \
                          - (T)3 * e[m + 4]) * ita;                                 \
            e[n] = last; e[n + 1] = next_to_last;                                   \
            for (long i = n - 4; i < n - 2; ++i) {                                  \
                T w = e[i + 4] * itb;                                               \
                Nh[i + 1] += w; Nh[i] -= (T)3 * w; Nh[i - 1] += (T)3 * w; Nh[i - 2] -= w; \
            }                                                                       \
            e[n] = 0; e[n + 1] = 0;                                                 \
            TVD_ADJOINT_ADD(T, MINMOD_SLOPE, xq, Dq, Nq)                            \
            TVD_ADJOINT_ADD(T, MINMOD_SLOPE, flux, Df, gflux)                       \
            IVDEP for (long j = 0; j < n; ++j) {                                    \
                Nq[j] += (T)2 * xq[j] * gflux[j] * inv_h[j];                        \
                Nh[j] -= gflux[j] * flux[j] * inv_h[j];                             \
            }                                                                       \
            for (long j = 0; j < n; ++j) { Gh[j] = Nh[j]; Gq[j] = Nq[j]; }          \
        }                                                                           \
        g_scale[b] = gS;                                                            \
    }                                                                               \
    FLUSH_END                                                                       \
}
SHKADOV_ADJOINT(shkadov_adjoint_f32, float)
SHKADOV_ADJOINT(shkadov_adjoint_f64, double)

/* sloshing-v0: per substep k, on the fields ghosted at the walls (H = h mirrored, Q = 0
   in the ghost cells; n + 2 cells), the flux F = Q Q / H + ((g / 2) H) H, the speed
   s = |Q / H| + sqrt(g H), each face's c = max(s_left, s_right) (torch.maximum's: NaN
   if either is) and the Rusanov fluxes of h and q, then
     fh = -(Fh_right - Fh_left) / dx,  fq = -(Fq_right - Fq_left) / dx - accel_k,
     h <- h + c (3 fh - fh_prev),  q <- q + c (3 fq - fq_prev)  (c = dt / 2)
   with g a row's own. states [rows, substeps, 2, n] (h, q); work 6 (n + 2) values. */
#define TORCH_MAX(a, b) ((a) != (a) || (b) != (b) ? (a) + (b) : ((a) > (b) ? (a) : (b)))
#define SLOSHING_GHOSTS(T, SQRT)                                                    \
            H[0] = xh[0]; H[n + 1] = xh[n - 1]; Q[0] = 0; Q[n + 1] = 0;             \
            for (long i = 0; i < n; ++i) { H[i + 1] = xh[i]; Q[i + 1] = xq[i]; }    \
            for (long j = 0; j < n + 2; ++j) {                                      \
                T r = Q[j] / H[j];                                                  \
                flux[j] = (Q[j] * Q[j]) / H[j] + (half_g * H[j]) * H[j];            \
                speed[j] = (r < 0 ? -r : r) + SQRT(g * H[j]);                       \
            }                                                                       \
            for (long j = 0; j <= n; ++j) cf[j] = TORCH_MAX(speed[j], speed[j + 1]);
#define SLOSHING_ACTION(NAME, T, SQRT)                                              \
void NAME(T *restrict h_out, T *restrict q_out, T *restrict fh_out, T *restrict fq_out, \
          T *restrict states, T *restrict work, const T *restrict h0, const T *restrict q0, \
          const T *restrict fh0, const T *restrict fq0, const T *restrict accel,    \
          const T *restrict gs, long rows, long n, long substeps, T dx, T c) {      \
    const long m = n + 2;                                                           \
    T *restrict H = work, *restrict Q = work + m, *restrict flux = work + 2 * m;   \
    T *restrict speed = work + 3 * m, *restrict cf = work + 4 * m, *restrict FH = work + 5 * m; \
    for (long b = 0; b < rows; ++b) {                                               \
        T *restrict fhp = fh_out + b * n, *restrict fqp = fq_out + b * n;           \
        T *restrict first = states + b * substeps * 2 * n, g = gs[b], half_g = (T)0.5 * g; \
        for (long i = 0; i < n; ++i) {                                              \
            first[i] = h0[b * n + i]; first[n + i] = q0[b * n + i];                 \
            fhp[i] = fh0[b * n + i]; fqp[i] = fq0[b * n + i];                       \
        }                                                                           \
        for (long k = 0; k < substeps; ++k) {                                       \
            const T *restrict xh = states + (b * substeps + k) * 2 * n, *restrict xq = xh + n; \
            T *restrict nh = k + 1 < substeps ? states + (b * substeps + k + 1) * 2 * n : h_out + b * n; \
            T *restrict nq = k + 1 < substeps ? nh + n : q_out + b * n;            \
            T acc = accel[k * rows + b];                                            \
            SLOSHING_GHOSTS(T, SQRT)                                                \
            for (long j = 0; j <= n; ++j) {                                         \
                FH[j] = (T)0.5 * (Q[j] + Q[j + 1]) - ((T)0.5 * cf[j]) * (H[j + 1] - H[j]); \
                cf[j] = (T)0.5 * (flux[j] + flux[j + 1]) - ((T)0.5 * cf[j]) * (Q[j + 1] - Q[j]); \
            }                                                                       \
            for (long i = 0; i < n; ++i) {                                          \
                T fh = (-(FH[i + 1] - FH[i])) / dx, fq = (-(cf[i + 1] - cf[i])) / dx - acc; \
                nh[i] = xh[i] + c * ((T)3 * fh - fhp[i]);                           \
                nq[i] = xq[i] + c * ((T)3 * fq - fqp[i]);                           \
                fhp[i] = fh;                                                        \
                fqp[i] = fq;                                                        \
            }                                                                       \
        }                                                                           \
    }                                                                               \
}
SLOSHING_ACTION(sloshing_action_f32, float, __builtin_sqrtf)
SLOSHING_ACTION(sloshing_action_f64, double, __builtin_sqrt)

/* Its adjoint: from the gradients of the action's new (h, q, fh, fq), those of its
   (h, q, fh_prev, fq_prev), of each substep's acceleration (g_accel [substeps, rows]) and
   of each row's g. The faces' arrays sit one place in, between zeros, so that each ghost
   cell gathers from the face on its left and the one on its right alike; a tie of the
   speeds shares the face's gradient half and half, as torch.maximum's backward does.
   The speeds are the forward's own (its divisions and roots), so that each maximum
   picks the same side; the rest multiplies by 1 / h, 1 / dx and 1 / g. The sums over
   cells (of the acceleration's and g's gradients) run after the loops that fill
   their terms, which then vectorise; the ghost cells at the ends read a speed past
   them whose weight meets a zero face. work 18 (n + 2) + 6 values. */
#define SLOSHING_ADJOINT(NAME, T, SQRT)                                             \
void NAME(T *restrict gh_out, T *restrict gq_out, T *restrict gfh_out, T *restrict gfq_out, \
          T *restrict g_accel, T *restrict g_g, T *restrict work, const T *restrict states, \
          const T *restrict gs, const T *restrict gh, const T *restrict gq,         \
          const T *restrict gfh, const T *restrict gfq, long rows, long n, long substeps, \
          T dx, T c) {                                                              \
    FLUSH_BEGIN                                                                     \
    const long m = n + 2;                                                           \
    T *restrict H = work, *restrict Q = work + m;                                   \
    T *restrict speed = work + 3 * m, *restrict cf = work + 4 * m;                 \
    T *restrict ah = work + 5 * m, *restrict aq = work + 6 * m;                    \
    T *restrict gFH = work + 7 * m + 1, *restrict gFQ = work + 8 * m + 2;          \
    T *restrict gc = work + 9 * m + 3, *restrict hc = work + 10 * m + 4;           \
    T *restrict GH = work + 11 * m + 5, *restrict GQ = work + 12 * m + 5;          \
    T *restrict ratio = work + 14 * m + 6, *restrict inv_h = work + 15 * m + 6;    \
    T *restrict roots = work + 16 * m + 6, *restrict dq = work + 17 * m + 6, idx = (T)1 / dx; \
    for (long j = 0; j < 14 * m + 6; ++j) work[j] = 0;                              \
    for (long b = 0; b < rows; ++b) {                                               \
        T *restrict Gh = gh_out + b * n, *restrict Gq = gq_out + b * n;             \
        T *restrict Gfh = gfh_out + b * n, *restrict Gfq = gfq_out + b * n;         \
        T g = gs[b], half_g = (T)0.5 * g, inv_g = (T)1 / g, gg = 0;                 \
        for (long i = 0; i < n; ++i) {                                              \
            Gh[i] = gh[b * n + i]; Gq[i] = gq[b * n + i];                           \
            Gfh[i] = gfh[b * n + i]; Gfq[i] = gfq[b * n + i];                       \
        }                                                                           \
        for (long k = substeps - 1; k >= 0; --k) {                                  \
            const T *restrict xh = states + (b * substeps + k) * 2 * n, *restrict xq = xh + n; \
            PREFETCH_NEXT_STATE(T, 2 * n)                                           \
            T gacc = 0, gcells = 0;                                                 \
            H[0] = xh[0]; H[n + 1] = xh[n - 1]; Q[0] = 0; Q[n + 1] = 0;             \
            for (long i = 0; i < n; ++i) { H[i + 1] = xh[i]; Q[i + 1] = xq[i]; }    \
            IVDEP for (long j = 0; j < m; ++j) {  /* the speeds as the forward's, for its maxima */ \
                T r = Q[j] / H[j], root = SQRT(g * H[j]);                           \
                speed[j] = (r < 0 ? -r : r) + root;                                 \
                ratio[j] = r; inv_h[j] = (T)1 / H[j]; roots[j] = root;              \
            }                                                                       \
            for (long j = 0; j <= n; ++j) cf[j] = TORCH_MAX(speed[j], speed[j + 1]); \
            for (long i = 0; i < n; ++i) {                                          \
                T sh = c * Gh[i], sq = c * Gq[i];                                   \
                T dfh = Gfh[i] + (T)3 * sh, dfq = Gfq[i] + (T)3 * sq;               \
                dq[i] = dfq;                                                        \
                ah[i + 1] = -(dfh * idx);                                           \
                aq[i + 1] = -(dfq * idx);                                           \
                Gfh[i] = -sh;                                                       \
                Gfq[i] = -sq;                                                       \
            }                                                                       \
            for (long i = 0; i < n; ++i) gacc -= dq[i];                             \
            g_accel[k * rows + b] = gacc;                                           \
            IVDEP for (long j = 0; j <= n; ++j) {  /* face j between ghost cells j, j + 1 */ \
                T a = ah[j] - ah[j + 1], e = aq[j] - aq[j + 1];                     \
                gFH[j] = a; gFQ[j] = e; hc[j] = (T)0.5 * cf[j];                     \
                gc[j] = -(((T)0.5 * a) * (H[j + 1] - H[j])) - ((T)0.5 * e) * (Q[j + 1] - Q[j]); \
            }                                                                       \
            IVDEP for (long j = 0; j < m; ++j) {  /* ghost cell j: faces j - 1 (its left) and j */ \
                T s = speed[j], left = speed[j - 1], right = speed[j + 1];          \
                T wl = s > left ? (T)1 : (s == left ? (T)0.5 : (T)0);               \
                T wr = s > right ? (T)1 : (s == right ? (T)0.5 : (T)0);             \
                T gsp = gc[j - 1] * wl + gc[j] * wr;                                \
                T gfl = (T)0.5 * gFQ[j] + (T)0.5 * gFQ[j - 1];                      \
                T gq_ = (T)0.5 * gFH[j] + (T)0.5 * gFH[j - 1] + hc[j] * gFQ[j] - hc[j - 1] * gFQ[j - 1]; \
                T gh_ = hc[j] * gFH[j] - hc[j - 1] * gFH[j - 1];                    \
                T r = ratio[j], ih = inv_h[j];                                      \
                /* 1 / sqrt(g H) as sqrt(g H) / (g H): no second root or division */ \
                T gr = gsp * (T)((r > 0) - (r < 0)), groot = (T)0.5 * gsp * (roots[j] * ih * inv_g); \
                gq_ += gr * ih;                                                     \
                gh_ -= gr * r * ih;                                                 \
                gh_ += groot * g;                                                   \
                gq_ += (T)2 * Q[j] * gfl * ih;                                      \
                gh_ -= gfl * (r * r);                                               \
                gh_ += gfl * (half_g * H[j]) + (gfl * H[j]) * half_g;               \
                roots[j] = groot * H[j] + (T)0.5 * ((gfl * H[j]) * H[j]);  /* g's share */ \
                GH[j] = gh_; GQ[j] = gq_;                                           \
            }                                                                       \
            for (long j = 0; j < m; ++j) gcells += roots[j];                        \
            gg += gcells;                                                           \
            for (long i = 0; i < n; ++i) { Gh[i] += GH[i + 1]; Gq[i] += GQ[i + 1]; } \
            Gh[0] += GH[0];                                                         \
            Gh[n - 1] += GH[n + 1];                                                 \
        }                                                                           \
        g_g[b] = gg;                                                                \
    }                                                                               \
    FLUSH_END                                                                       \
}
SLOSHING_ADJOINT(sloshing_adjoint_f32, float, __builtin_sqrtf)
SLOSHING_ADJOINT(sloshing_adjoint_f64, double, __builtin_sqrt)

/* The adjoint of the staggered grid's explicit momentum terms (centred fluxes of
   face-averaged velocities, and nu times the second differences): from the gradients
   gu [nx - 1][ny][B] and gv [nx][ny - 1][B] of the terms on the interior faces, the
   gradients du [nx + 1][ny + 2][B] and dv [nx + 2][ny + 1][B] of the ghosted
   velocities, each term adding to the faces it read. cx and cy hold each axis's
   multipliers: the differences across the interior faces' control volumes (n - 1)
   and the cells' (n), then the second differences' outer coefficients at the
   interior faces (minus, plus: n - 1 each) and at the cells (n each). nu [B]. Inlined
   for 8 and 16 members (see INLINED). */
#define MOMENTUM_ADJOINT(NAME, T)                                                   \
INLINED void NAME##_rows(                                                           \
          T *du, T *dv, const T *u, const T *v, const T *gu, const T *gv,           \
          const T *nu, const T *cx, const T *cy, long nx, long ny, long B) {         \
    const long uc = (ny + 2) * B, vc = (ny + 1) * B;                                \
    const T *xdf = cx, *xdc = cx + (nx - 1), *xfm = xdc + nx, *xfp = xfm + (nx - 1); \
    const T *xcm = xfp + (nx - 1), *xcp = xcm + nx;                                 \
    const T *ydf = cy, *ydc = cy + (ny - 1), *yfm = ydc + ny, *yfp = yfm + (ny - 1); \
    const T *ycm = yfp + (ny - 1), *ycp = ycm + ny;                                 \
    for (long k = 0; k < (nx + 1) * uc; ++k) du[k] = 0;                             \
    for (long k = 0; k < (nx + 2) * vc; ++k) dv[k] = 0;                             \
    for (long i = 1; i < nx; ++i)                                                   \
        for (long j = 0; j < ny; ++j) {                                             \
            const T *g = gu + ((i - 1) * ny + j) * B;                               \
            const T *uu = u + i * uc + (j + 1) * B, *vv = v + i * vc + j * B;       \
            T *d = du + i * uc + (j + 1) * B, *e = dv + i * vc + j * B;             \
            const T sx = xdf[i - 1], sy = ydc[j];                                   \
            const T fm = xfm[i - 1], fp = xfp[i - 1], hm = ycm[j], hp = ycp[j];     \
            const T fc = -(fm + fp) - (hm + hp);                                    \
            IVDEP                                                                   \
            for (long m = 0; m < B; ++m) {                                          \
                const T G = g[m], a = -G * sx, b = -(T)0.5 * G * sy, L = nu[m] * G; \
                const T pe = a * ((T)0.5 * (uu[m] + uu[uc + m]));                   \
                const T pw = a * ((T)0.5 * (uu[m - uc] + uu[m]));                   \
                const T un = (T)0.5 * (uu[m] + uu[B + m]), us = (T)0.5 * (uu[m - B] + uu[m]); \
                const T vn = (T)0.5 * (vv[B + m] + vv[vc + B + m]), vs = (T)0.5 * (vv[m] + vv[vc + m]); \
                const T qn = b * vn, qs = b * vs, rn = b * un, rs = b * us;         \
                d[m] += (pe - pw) + (qn - qs) + L * fc;                             \
                d[uc + m] += pe + L * fp;                                           \
                d[m - uc] += L * fm - pw;                                           \
                d[B + m] += qn + L * hp;                                            \
                d[m - B] += L * hm - qs;                                            \
                e[B + m] += rn;                                                     \
                e[vc + B + m] += rn;                                                \
                e[m] -= rs;                                                         \
                e[vc + m] -= rs;                                                    \
            }                                                                       \
        }                                                                           \
    for (long c = 0; c < nx; ++c)                                                   \
        for (long k = 1; k < ny; ++k) {                                             \
            const T *g = gv + (c * (ny - 1) + (k - 1)) * B;                         \
            const T *vv = v + (c + 1) * vc + k * B, *uu = u + c * uc + k * B;       \
            T *d = dv + (c + 1) * vc + k * B, *e = du + c * uc + k * B;             \
            const T sy = ydf[k - 1], sx = xdc[c];                                   \
            const T fm = yfm[k - 1], fp = yfp[k - 1], hm = xcm[c], hp = xcp[c];     \
            const T fc = -(hm + hp) - (fm + fp);                                    \
            IVDEP                                                                   \
            for (long m = 0; m < B; ++m) {                                          \
                const T G = g[m], a = -G * sy, b = -(T)0.5 * G * sx, L = nu[m] * G; \
                const T pn = a * ((T)0.5 * (vv[m] + vv[B + m]));                    \
                const T ps = a * ((T)0.5 * (vv[m - B] + vv[m]));                    \
                const T ve = (T)0.5 * (vv[m] + vv[vc + m]), vw = (T)0.5 * (vv[m - vc] + vv[m]); \
                const T ue = (T)0.5 * (uu[uc + m] + uu[uc + B + m]), uw = (T)0.5 * (uu[m] + uu[B + m]); \
                const T qe = b * ue, qw = b * uw, re = b * ve, rw = b * vw;         \
                d[m] += (pn - ps) + (qe - qw) + L * fc;                             \
                d[B + m] += pn + L * fp;                                            \
                d[m - B] += L * fm - ps;                                            \
                d[vc + m] += qe + L * hp;                                           \
                d[m - vc] += L * hm - qw;                                           \
                e[uc + m] += re;                                                    \
                e[uc + B + m] += re;                                                \
                e[m] -= rw;                                                         \
                e[B + m] -= rw;                                                     \
            }                                                                       \
        }                                                                           \
}                                                                                   \
void NAME(T *du, T *dv, const T *u, const T *v, const T *gu, const T *gv,           \
          const T *nu, const T *cx, const T *cy, long nx, long ny, long B) {         \
    if (B == 8) NAME##_rows(du, dv, u, v, gu, gv, nu, cx, cy, nx, ny, 8);           \
    else if (B == 16) NAME##_rows(du, dv, u, v, gu, gv, nu, cx, cy, nx, ny, 16);    \
    else NAME##_rows(du, dv, u, v, gu, gv, nu, cx, cy, nx, ny, B);                  \
}
MOMENTUM_ADJOINT(momentum_adjoint_f32, float)
MOMENTUM_ADJOINT(momentum_adjoint_f64, double)
"""

_FLAGS = ("-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math", "-fno-math-errno")
# the vector instructions of the machine that builds (and so runs) the library, where
# the compiler knows them: without contraction or reassociation (the flags above) a
# vector lane computes what the scalar code does, bit for bit
_HOST = ("-march=native",)

_lock = threading.Lock()
_library: ctypes.CDLL | None = None
_tried = False


def _compile(compiler: str, flags: tuple[str, ...], source: str, library: str) -> None:
    subprocess.run([compiler, *flags, source, "-o", library], check=True, capture_output=True, timeout=120)


def _build() -> ctypes.CDLL | None:
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        return None
    folder = tempfile.mkdtemp(prefix="beacon-torch-native-")
    source, library = os.path.join(folder, "sweep.c"), os.path.join(folder, "sweep.so")
    with open(source, "w") as f:
        f.write(_SOURCE)
    try:
        try:
            _compile(compiler, (*_FLAGS, *_HOST), source, library)
        except subprocess.CalledProcessError:
            _compile(compiler, _FLAGS, source, library)
        lib = ctypes.CDLL(library)
    except (OSError, subprocess.SubprocessError) as err:
        warnings.warn(
            f"beacon_torch: the C kernels could not be built ({err}); using the slower tensor paths",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    finally:
        # the loaded library stays mapped after its file is gone
        shutil.rmtree(folder, ignore_errors=True)
    # the arrays go as their addresses (an integer each): a typed pointer's cast costs
    # microseconds a call, and the caller has chosen the kernel of the tensors' dtype
    pointer, size = ctypes.c_void_p, ctypes.c_long
    for suffix, ctype in (("f32", ctypes.c_float), ("f64", ctypes.c_double)):
        for name, arrays in (("sweep", 4), ("lines", 5), ("sweep_adjoint", 7), ("momentum_adjoint", 9)):
            fn = getattr(lib, f"{name}_{suffix}")
            fn.argtypes = (*(pointer,) * arrays, size, size, size)
            fn.restype = None
        fn = getattr(lib, f"tvd_adjoint_{suffix}")
        fn.argtypes = (*(pointer,) * 4, size, size, ctype, size)
        fn.restype = None
        for name, arrays, numbers in (
            ("burgers_action", 8, 2),
            ("burgers_adjoint", 8, 2),
            ("shkadov_action", 15, 4),
            ("shkadov_adjoint", 16, 4),
            ("sloshing_action", 12, 2),
            ("sloshing_adjoint", 13, 2),
        ):
            fn = getattr(lib, f"{name}_{suffix}")
            fn.argtypes = (*(pointer,) * arrays, size, size, size, *(ctype,) * numbers)
            fn.restype = None
    return lib


def library() -> ctypes.CDLL | None:
    """The compiled kernels, built on the first call of the process (None where they
    cannot be, or ``BEACON_TORCH_NATIVE=0``)."""
    global _library, _tried
    if os.environ.get("BEACON_TORCH_NATIVE", "1") == "0":
        return None
    if not _tried:
        if torch.compiler.is_compiling():
            # a trace can neither run the compiler nor hold a lock: the code being
            # traced takes the tensor paths, and its guard on _tried compiles it again
            # once the library is built (the env's own compiled calls build it first)
            return None
        with _lock:
            if not _tried:
                _library = _build()
                _tried = True
    return _library


_KERNELS = {torch.float32: ("f32", ctypes.c_float), torch.float64: ("f64", ctypes.c_double)}


def applies(device, dtype) -> bool:
    """Whether :func:`sweep` and :func:`lines` run for tensors of this device and dtype
    (building the kernels on the first call)."""
    return torch.device(device or "cpu").type == "cpu" and dtype in _KERNELS and library() is not None


def recording(*tensors: torch.Tensor) -> bool:
    """Whether autograd records an operation on these tensors."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def takes(*tensors: torch.Tensor) -> bool:
    """Whether the kernels run on these tensors now: CPU tensors of one kernel dtype
    (the caller has asked :func:`applies` once)."""
    first = tensors[0]
    return first.device.type == "cpu" and first.dtype in _KERNELS and all(t.dtype == first.dtype for t in tensors)


def _call(name: str, first: torch.Tensor, *rest: torch.Tensor, sizes: tuple[int, ...], outs=None) -> torch.Tensor:
    """The kernel ``name`` from ``first`` and the other arrays (made contiguous) into a
    new tensor shaped like ``first`` (or into new tensors shaped like each of ``outs``,
    returned as a tuple): the kernels write their results out of place, so that no copy
    of an input is needed for the operator's functional form."""
    # the switch BEACON_TORCH_NATIVE is read where the caller decides (applies), not here
    lib = _library if _tried else library()
    if first.device.type != "cpu" or first.dtype not in _KERNELS or lib is None:
        raise RuntimeError(f"{name}: the C kernel does not apply here (see native.applies)")
    arrays = [t.contiguous() for t in (first, *rest)]
    results = [torch.empty(like.shape, dtype=first.dtype) for like in (outs or (arrays[0],))]
    getattr(lib, f"{name}_{_KERNELS[first.dtype][0]}")(*(t.data_ptr() for t in (*results, *arrays)), *sizes)
    return tuple(results) if outs else results[0]


def tvd_adjoint(f: torch.Tensor, grad: torch.Tensor, dx: float, minmod: bool) -> torch.Tensor:
    """The gradient of ``f`` (``[..., n]``) of the TVD derivative of each of its rows
    (:func:`beacon_torch.numerics.fluxes.tvd_derivative` with van Leer's limiter, or
    minmod's), from the gradient ``grad`` (``[..., n - 2]``) of that derivative: the C
    kernel. Only where :func:`applies` and :func:`takes`."""
    lib = _library if _tried else library()
    if lib is None or not takes(f, grad):
        raise RuntimeError("tvd_adjoint: the C kernel does not apply here (see native.applies)")
    n = f.shape[-1]
    if n < 4 or grad.shape != (*f.shape[:-1], n - 2):
        raise ValueError(f"tvd_adjoint: rows {tuple(f.shape)} and their gradient {tuple(grad.shape)} do not fit")
    f, grad = f.contiguous(), grad.contiguous()
    out, work = torch.empty_like(f), torch.empty(2 * n, dtype=f.dtype)
    arrays = (t.data_ptr() for t in (out, work, f, grad))
    getattr(lib, f"tvd_adjoint_{_KERNELS[f.dtype][0]}")(*arrays, f.numel() // n, n, dx, int(minmod))
    return out


# The stored substeps of the differentiated actions, kept for the next action once
# nothing else holds them. A fresh buffer of several MB costs the process a page fault
# a page (about 1 ms an action on burgers at 64 members, a third of its C forward
# loop), and the actions of a horizon ask for the same sizes again and again. A
# buffer is handed out again only when the cache's reference is the last one to its
# storage (the graph that saved it is gone); at most _KEPT_BYTES are kept.
_KEPT_BYTES = 256 << 20
_SMALLEST_KEPT = 1 << 20
_kept: list[torch.Tensor] = []
_kept_lock = threading.Lock()


def _unused(buffer: torch.Tensor) -> bool:
    # the cache's tensor and the storage object asked for here are its only holders
    return torch._C._storage_Use_Count(buffer.untyped_storage()._cdata) == 2


def stored_substeps(like: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """An uninitialised tensor of ``shape`` and ``like``'s dtype and device for an
    action's stored substeps: a kept buffer of that size that nothing holds any more
    where there is one, else a new one, kept while the cache has room."""
    numel = 1
    for size in shape:
        numel *= size
    nbytes = numel * like.element_size()
    if nbytes < _SMALLEST_KEPT or not hasattr(torch._C, "_storage_Use_Count"):
        return like.new_empty(shape)
    with _kept_lock:
        free = [b for b in _kept if _unused(b)]
        for buffer in free:
            if buffer.dtype == like.dtype and buffer.device == like.device and buffer.numel() == numel:
                return buffer.view(shape)
        held = sum(b.numel() * b.element_size() for b in _kept)
        for buffer in free:  # unused buffers of other sizes make room first
            if held + nbytes <= _KEPT_BYTES:
                break
            # by identity: list.remove compares tensors with ==, elementwise
            del _kept[next(i for i, b in enumerate(_kept) if b is buffer)]
            held -= buffer.numel() * buffer.element_size()
        buffer = like.new_empty(numel)
        if held + nbytes <= _KEPT_BYTES:
            _kept.append(buffer)
        return buffer.view(shape)


def _rows(name: str, *tensors: torch.Tensor) -> ctypes.CDLL:
    lib = _library if _tried else library()
    if lib is None or not takes(*tensors):
        raise RuntimeError(f"{name}: the C kernel does not apply here (see native.applies)")
    return lib


def burgers_action(
    u: torch.Tensor,
    u_prev: torch.Tensor,
    inlet: torch.Tensor,
    forcing: torch.Tensor,
    substeps: int,
    dx: float,
    c: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``substeps`` substeps of the inviscid Burgers flow from the rows ``(u, u_prev)``
    (``[rows, n]``) with the inlet values ``inlet`` (``[rows, 1]``) and the forcing
    ``forcing`` (``[rows, n - 2]``) held: the new ``(u, u_prev)`` and the states
    ``[rows, substeps, n]`` (u at the start of each substep) that :func:`burgers_adjoint`
    reads. The C kernel (see its source); only where :func:`applies` and :func:`takes`."""
    lib = _rows("burgers_action", u, u_prev, inlet, forcing)
    rows, n = u.shape
    if n < 4 or substeps < 1 or u_prev.shape != u.shape or inlet.shape != (rows, 1) or forcing.shape != (rows, n - 2):
        raise ValueError(
            f"burgers_action: rows {tuple(u.shape)}, {tuple(u_prev.shape)}, inlet {tuple(inlet.shape)} and forcing "
            f"{tuple(forcing.shape)} do not fit, or {substeps} substeps"
        )
    arrays = [t.contiguous() for t in (u, u_prev, inlet, forcing)]
    u_out, p_out = torch.empty_like(arrays[0]), torch.empty_like(arrays[0])
    states, work = stored_substeps(u, (rows, substeps, n)), u.new_empty(3 * n)
    pointers = (t.data_ptr() for t in (u_out, p_out, states, work, *arrays))
    getattr(lib, f"burgers_action_{_KERNELS[u.dtype][0]}")(*pointers, rows, n, substeps, dx, c)
    return u_out, p_out, states


def burgers_adjoint(
    states: torch.Tensor, grad_u: torch.Tensor, grad_u_prev: torch.Tensor, dx: float, c: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The gradients of :func:`burgers_action`'s ``(u, u_prev, inlet, forcing)`` from
    those of its new ``(u, u_prev)`` and its ``states``: the C kernel, the substeps
    in reverse."""
    lib = _rows("burgers_adjoint", states, grad_u, grad_u_prev)
    rows, substeps, n = states.shape
    if grad_u.shape != (rows, n) or grad_u_prev.shape != (rows, n):
        raise ValueError(
            f"burgers_adjoint: states {tuple(states.shape)} and gradients {tuple(grad_u.shape)}, "
            f"{tuple(grad_u_prev.shape)} do not fit"
        )
    arrays = [t.contiguous() for t in (states, grad_u, grad_u_prev)]
    gu, gp = torch.empty_like(arrays[1]), torch.empty_like(arrays[1])
    g_inlet, g_forcing, work = states.new_empty((rows, 1)), states.new_empty((rows, n - 2)), states.new_empty(6 * n)
    pointers = (t.data_ptr() for t in (gu, gp, g_inlet, g_forcing, work, *arrays))
    getattr(lib, f"burgers_adjoint_{_KERNELS[states.dtype][0]}")(*pointers, rows, n, substeps, dx, c)
    return gu, gp, g_inlet, g_forcing


def shkadov_action(
    h: torch.Tensor,
    q: torch.Tensor,
    dh_prev: torch.Tensor,
    dq_prev: torch.Tensor,
    forcing_prev: torch.Tensor,
    forcing_new: torch.Tensor,
    alpha: torch.Tensor,
    inlet: torch.Tensor,
    scale: torch.Tensor,
    dx: float,
    c: float,
    third_a: float,
    third_b: float,
) -> tuple[torch.Tensor, ...]:
    """The substeps of shkadov-v0's action (one for each of ``alpha``'s weights) from the
    rows ``(h, q)`` (``[rows, n]``) and ``(dh_prev, dq_prev)`` (``[rows, n - 2]``), with the
    forcing interpolated from ``forcing_prev`` to ``forcing_new`` (``[rows, n - 2]``), the
    inlet values ``inlet`` (``[substeps, rows, 1]``) and each row's ``scale`` = 5 delta
    (``[rows]``): the new ``(h, q, dh_prev, dq_prev)`` and the states
    ``[rows, substeps, 2, n]`` that :func:`shkadov_adjoint` reads. The C kernel."""
    lib = _rows("shkadov_action", h, q, dh_prev, dq_prev, forcing_prev, forcing_new, alpha, inlet, scale)
    rows, n = h.shape
    substeps = alpha.shape[0]
    inner = (rows, n - 2)
    if (
        n < 8
        or q.shape != h.shape
        or any(t.shape != inner for t in (dh_prev, dq_prev, forcing_prev, forcing_new))
        or alpha.shape != (substeps,)
        or inlet.shape != (substeps, rows, 1)
        or scale.shape != (rows,)
    ):
        raise ValueError(f"shkadov_action: the rows {tuple(h.shape)} and the action's inputs do not fit")
    arrays = [t.contiguous() for t in (h, q, dh_prev, dq_prev, forcing_prev, forcing_new, alpha, inlet, scale)]
    outs = [torch.empty_like(t) for t in arrays[:4]]
    states, work = stored_substeps(h, (rows, substeps, 2, n)), h.new_empty(6 * n)
    pointers = (t.data_ptr() for t in (*outs, states, work, *arrays))
    getattr(lib, f"shkadov_action_{_KERNELS[h.dtype][0]}")(*pointers, rows, n, substeps, dx, c, third_a, third_b)
    return (*outs, states)


def shkadov_adjoint(
    states: torch.Tensor,
    alpha: torch.Tensor,
    scale: torch.Tensor,
    grads: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    dx: float,
    c: float,
    third_a: float,
    third_b: float,
) -> tuple[torch.Tensor, ...]:
    """The gradients of :func:`shkadov_action`'s ``(h, q, dh_prev, dq_prev,
    forcing_prev, forcing_new, inlet, scale)`` from those of its new ``(h, q, dh_prev,
    dq_prev)`` and its ``states``: the C kernel, the substeps in reverse."""
    lib = _rows("shkadov_adjoint", states, alpha, scale, *grads)
    rows, substeps, _, n = states.shape
    if tuple(g.shape for g in grads) != ((rows, n), (rows, n), (rows, n - 2), (rows, n - 2)):
        raise ValueError(f"shkadov_adjoint: states {tuple(states.shape)} and the gradients do not fit")
    arrays = [t.contiguous() for t in (states, alpha, scale, *grads)]
    outs = [torch.empty_like(g) for g in arrays[3:]] + [states.new_empty((rows, n - 2)) for _ in range(2)]
    g_inlet, g_scale, work = states.new_empty((substeps, rows, 1)), states.new_empty(rows), states.new_empty(14 * n + 8)
    pointers = (t.data_ptr() for t in (*outs, g_inlet, g_scale, work, *arrays))
    getattr(lib, f"shkadov_adjoint_{_KERNELS[states.dtype][0]}")(*pointers, rows, n, substeps, dx, c, third_a, third_b)
    return (*outs, g_inlet, g_scale)


def sloshing_action(
    h: torch.Tensor,
    q: torch.Tensor,
    fh_prev: torch.Tensor,
    fq_prev: torch.Tensor,
    accel: torch.Tensor,
    g: torch.Tensor,
    dx: float,
    c: float,
) -> tuple[torch.Tensor, ...]:
    """The substeps of sloshing-v0's action (one for each row of ``accel``,
    ``[substeps, rows]``, the tank's acceleration) from the rows ``(h, q, fh_prev,
    fq_prev)`` (``[rows, n]``) with each row's gravity ``g`` (``[rows]``): the new
    fields and the states ``[rows, substeps, 2, n]`` that :func:`sloshing_adjoint`
    reads. The C kernel."""
    lib = _rows("sloshing_action", h, q, fh_prev, fq_prev, accel, g)
    rows, n = h.shape
    substeps = accel.shape[0]
    if (
        n < 2
        or any(t.shape != h.shape for t in (q, fh_prev, fq_prev))
        or accel.shape != (substeps, rows)
        or g.shape != (rows,)
    ):
        raise ValueError(f"sloshing_action: the rows {tuple(h.shape)} and the action's inputs do not fit")
    arrays = [t.contiguous() for t in (h, q, fh_prev, fq_prev, accel, g)]
    outs = [torch.empty_like(t) for t in arrays[:4]]
    states, work = stored_substeps(h, (rows, substeps, 2, n)), h.new_empty(6 * (n + 2))
    pointers = (t.data_ptr() for t in (*outs, states, work, *arrays))
    getattr(lib, f"sloshing_action_{_KERNELS[h.dtype][0]}")(*pointers, rows, n, substeps, dx, c)
    return (*outs, states)


def sloshing_adjoint(
    states: torch.Tensor, g: torch.Tensor, grads: tuple[torch.Tensor, ...], dx: float, c: float
) -> tuple[torch.Tensor, ...]:
    """The gradients of :func:`sloshing_action`'s ``(h, q, fh_prev, fq_prev, accel, g)``
    from those of its new fields and its ``states``: the C kernel, the substeps in
    reverse."""
    lib = _rows("sloshing_adjoint", states, g, *grads)
    rows, substeps, _, n = states.shape
    if any(t.shape != (rows, n) for t in grads) or len(grads) != 4:
        raise ValueError(f"sloshing_adjoint: states {tuple(states.shape)} and the gradients do not fit")
    arrays = [t.contiguous() for t in (states, g, *grads)]
    outs = [torch.empty_like(t) for t in arrays[2:]]
    g_accel, g_g, work = states.new_empty((substeps, rows)), states.new_empty(rows), states.new_empty(18 * (n + 2) + 6)
    pointers = (t.data_ptr() for t in (*outs, g_accel, g_g, work, *arrays))
    getattr(lib, f"sloshing_adjoint_{_KERNELS[states.dtype][0]}")(*pointers, rows, n, substeps, dx, c)
    return (*outs, g_accel, g_g)


def output_grads(grads: tuple, likes: tuple) -> tuple:
    """The gradients a backward pass of a whole action receives, a zero tensor shaped
    like its ``like`` where an output received none. The actions' Functions leave
    materialising them off: their stored substeps are an output too, and autograd
    would otherwise fill a zero gradient as large as them every action (about 2 ms of
    an 8 MB fill on burgers at 64 members)."""
    return tuple(torch.zeros_like(like) if g is None else g for g, like in zip(grads, likes, strict=True))


def rows_vmap(name: str, inputs: tuple[int | None, ...], outputs: tuple[int, ...]):
    """A vmap rule for the operator ``beacon_torch::name`` whose tensors hold rows
    (members) along the axis ``inputs[k]`` of its ``k``-th argument (None, and every
    argument past ``inputs``: the same for every row) and ``outputs[k]`` of its
    ``k``-th result: the mapped dimension joins the rows (as their outer part), the
    kernel runs once, and its results are split again. A mapped argument of the second
    kind is not supported."""

    def rule(info, in_dims, *args):
        size, given = info.batch_size, []
        for k, (t, dim) in enumerate(zip(args, in_dims, strict=True)):
            axis = inputs[k] if k < len(inputs) else None
            if axis is None:
                if dim is not None:
                    raise NotImplementedError(f"{name}: vmap over an argument shared by the rows")
                given.append(t)
                continue
            t = (
                t.unsqueeze(axis).expand(*t.shape[:axis], size, *t.shape[axis:])
                if dim is None
                else t.movedim(dim, axis)
            )
            given.append(t.flatten(axis, axis + 1))
        out = getattr(torch.ops.beacon_torch, name).default(*given)
        return tuple(o.unflatten(axis, (size, -1)) for o, axis in zip(out, outputs, strict=True)), outputs

    return rule


def _members_vmap(name: str, member_args: tuple[int, ...], outputs: int = 1):
    """A vmap rule for the operator ``beacon_torch::name`` whose arrays ``member_args``
    (their positions) end with the members' axis and whose others are the same for
    every member: the mapped
    dimension joins the members (``[..., B, V]`` as ``[..., B * V]``), the kernel runs
    once, and its results are split again. A mapped array of the second kind (a
    coefficient that would differ per mapped value) is not supported."""

    def rule(info, in_dims, *args):
        size = info.batch_size
        given = []
        for k, (t, dim) in enumerate(zip(args, in_dims, strict=True)):
            if k not in member_args:
                if dim is not None:
                    raise NotImplementedError(f"{name}: vmap over an argument shared by the members")
                given.append(t)
                continue
            t = t.unsqueeze(-1).expand(*t.shape, size) if dim is None else t.movedim(dim, -1)
            given.append(t.reshape(*t.shape[:-2], -1))
        out = getattr(torch.ops.beacon_torch, name).default(*given)
        split = lambda o: o.reshape(*o.shape[:-1], -1, size)
        if outputs == 1:
            out = split(out)
            return out, out.dim() - 1
        out = tuple(split(o) for o in out)
        return out, tuple(o.dim() - 1 for o in out)

    return rule


# The kernels are operators of torch's dispatcher, so that a compiled substep calls a
# loop inside its graph (no graph break), out of place as the graph's functional form
# wants. They are registered with torch.library's own calls rather than its
# ``custom_op`` wrapper, whose layers (an autograd kernel, an aliasing check, a
# redispatch) took more time a call than the tridiagonal solve of a cavity's step at 8
# members: their autograd is the autograd.Function around each (its forward runs with
# autograd off), and the dispatcher calls the kernel below directly.
_OPERATORS = torch.library.Library("beacon_torch", "FRAGMENT")


def operator(schema: str, kernel, fake, vmap, key: str = "CPU"):
    """The dispatcher's operator ``beacon_torch::NAME`` of ``schema`` (``NAME(Tensor x,
    ...) -> Tensor``): ``kernel`` runs it on ``key``'s tensors (the CPU's, or every
    device's with ``"CompositeExplicitAutograd"``), ``fake`` gives the shapes of its
    results to a compiler, and ``vmap``, the rule ``(info, in_dims, *args)``, maps it
    under ``torch.func.vmap``. Returns the operator, to call as a function."""
    name = schema.split("(", 1)[0]
    _OPERATORS.define(schema)
    _OPERATORS.impl(name, kernel, key)
    qualified = f"beacon_torch::{name}"
    torch.library.register_fake(qualified, fake, lib=_OPERATORS)
    torch.library.register_vmap(qualified, vmap, lib=_OPERATORS)
    return getattr(torch.ops.beacon_torch, name).default


def _sweep_kernel(s: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The published in-place sweep of ``s`` (ghosted, ``[nx + 2, ny + 2, B]``, the
    interior holding each cell's part from old values), written to a new tensor with
    the same ghosts: cell ``(i, j)`` becomes
    ``s[i, j] + a * s[i - 1, j] + b * s[i, j - 1]`` with the new values of its west and
    south neighbours, for the interior coefficients ``a``, ``b`` (``[nx, ny, B]``).
    Only where :func:`applies`; :func:`sweep` is its differentiable form."""
    nx, ny, members = a.shape
    if s.shape != (nx + 2, ny + 2, members) or b.shape != a.shape or not (s.dtype == a.dtype == b.dtype):
        raise ValueError(
            f"sweep: the field {tuple(s.shape)} and coefficients {tuple(a.shape)}, {tuple(b.shape)} do not fit"
        )
    return _call("sweep", s, a, b, sizes=(nx, ny, members))


def _new(t: torch.Tensor) -> torch.Tensor:
    return torch.empty_like(t, memory_format=torch.contiguous_format)


sweep_kernel = operator(
    "sweep(Tensor s, Tensor a, Tensor b) -> Tensor",
    _sweep_kernel,
    lambda s, a, b: _new(s),
    _members_vmap("sweep", (0, 1, 2)),
)


def _sweep_adjoint(
    grad: torch.Tensor, x: torch.Tensor, a: torch.Tensor, b: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The gradients of :func:`sweep`'s ``(s, a, b)`` from the gradient ``grad`` of its
    output ``x``: the reverse sweep (see the C source)."""
    nx, ny, members = a.shape
    return _call("sweep_adjoint", grad, x, a, b, sizes=(nx, ny, members), outs=(grad, a, a))


sweep_adjoint = operator(
    "sweep_adjoint(Tensor grad, Tensor x, Tensor a, Tensor b) -> (Tensor, Tensor, Tensor)",
    _sweep_adjoint,
    lambda grad, x, a, b: (_new(grad), _new(a), _new(a)),
    _members_vmap("sweep_adjoint", (0, 1, 2, 3), outputs=3),
)


class _Sweep(torch.autograd.Function):
    """:func:`sweep_kernel` with the reverse sweep as its backward pass."""

    generate_vmap_rule = True

    @staticmethod
    def forward(s: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return sweep_kernel(s, a, b)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        _, a, b = inputs
        ctx.save_for_backward(output, a, b)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, a, b = ctx.saved_tensors
        with torch.no_grad():  # differentiable once: the adjoint keeps no graph
            return sweep_adjoint(grad, x, a, b)


def sweep(s: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`sweep_kernel`, differentiable (its adjoint is :func:`sweep_adjoint`), under
    ``torch.func`` and ``torch.compile`` too."""
    return _Sweep.apply(s, a, b)


def _lines_kernel(
    f: torch.Tensor, lower: torch.Tensor, inv: torch.Tensor, upper: torch.Tensor, width: torch.Tensor
) -> torch.Tensor:
    """Solves, into a new tensor shaped like ``f`` (``[modes, n, B]``), one tridiagonal system along the
    second axis per mode and member, from its elimination: ``lower`` and ``inv``
    (``[modes, n]``: the multipliers below the diagonal and the inverse pivots) and
    ``upper`` (``[n]``: the entries above the diagonal, the same for every mode). A zero
    last pivot (a singular mode) gives the solution whose last value is 0. ``width``
    (``[n]``) makes each matrix ``diag(1 / width) S + shift`` with ``S`` symmetric (ones:
    a symmetric matrix), which its adjoint reads. Only where :func:`applies`;
    :func:`lines` is its differentiable form."""
    modes, n, members = f.shape
    if (
        lower.shape != (modes, n)
        or inv.shape != (modes, n)
        or upper.shape != (n,)
        or width.shape != (n,)
        or not (f.dtype == lower.dtype == inv.dtype == upper.dtype == width.dtype)
    ):
        raise ValueError(
            f"lines: the field {tuple(f.shape)} and elimination {tuple(lower.shape)}, "
            f"{tuple(inv.shape)}, {tuple(upper.shape)}, {tuple(width.shape)} do not fit"
        )
    return _call("lines", f, lower, inv, upper, sizes=(modes, n, members))


lines_kernel = operator(
    "lines(Tensor f, Tensor lower, Tensor inv, Tensor upper, Tensor width) -> Tensor",
    _lines_kernel,
    lambda f, lower, inv, upper, width: _new(f),
    _members_vmap("lines", (0,)),
)


class _Lines(torch.autograd.Function):
    """:func:`lines_kernel` with the same solve as its backward pass."""

    generate_vmap_rule = True

    @staticmethod
    def forward(f, lower, inv, upper, width) -> torch.Tensor:
        return lines_kernel(f, lower, inv, upper, width)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(*inputs[1:])

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        # each solve is x = P f with P = T^-1 (or, singular, the leading block's inverse
        # and a zero last row and column), T = diag(1 / w) S + shift: P^T = W P W^-1,
        # the same solve between two scalings by the widths (ones: no scaling)
        lower, inv, upper, width = ctx.saved_tensors
        w = width[:, None]
        with torch.no_grad():  # differentiable once: the adjoint keeps no graph
            return w * lines_kernel(grad / w, lower, inv, upper, width), None, None, None, None


def lines(f: torch.Tensor, lower: torch.Tensor, inv: torch.Tensor, upper: torch.Tensor, width: torch.Tensor):
    """:func:`lines_kernel`, differentiable in ``f`` (the elimination is a constant of
    the grid), under ``torch.func`` and ``torch.compile`` too."""
    return _Lines.apply(f, lower, inv, upper, width)


def _momentum_adjoint(
    u: torch.Tensor,
    v: torch.Tensor,
    gu: torch.Tensor,
    gv: torch.Tensor,
    nu: torch.Tensor,
    cx: torch.Tensor,
    cy: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The gradients of the ghosted velocities ``u`` (``[nx + 1, ny + 2, B]``) and ``v``
    (``[nx + 2, ny + 1, B]``) of the staggered momentum terms
    (:func:`beacon_torch.numerics.staggered.tendency`) from ``gu`` and ``gv``, the
    gradients of its results: the C kernel, with the viscosity ``nu`` (``[B]``) and the
    axes' multipliers ``cx``, ``cy`` (see the C source;
    :func:`beacon_torch.numerics.staggered.multipliers`)."""
    nx, ny, members = u.shape[0] - 1, u.shape[1] - 2, u.shape[2]
    if (
        v.shape != (nx + 2, ny + 1, members)
        or gu.shape != (nx - 1, ny, members)
        or gv.shape != (nx, ny - 1, members)
        or nu.shape != (members,)
        or cx.shape != (6 * nx - 3,)
        or cy.shape != (6 * ny - 3,)
    ):
        raise ValueError(f"momentum_adjoint: the velocities {tuple(u.shape)}, {tuple(v.shape)} and the rest do not fit")
    return _call("momentum_adjoint", u, v, gu, gv, nu, cx, cy, sizes=(nx, ny, members), outs=(u, v))


momentum_adjoint = operator(
    "momentum_adjoint(Tensor u, Tensor v, Tensor gu, Tensor gv, Tensor nu, Tensor cx, Tensor cy) -> (Tensor, Tensor)",
    _momentum_adjoint,
    lambda u, v, gu, gv, nu, cx, cy: (_new(u), _new(v)),
    _members_vmap("momentum_adjoint", (0, 1, 2, 3, 4), outputs=2),
)
