/* The fused CPU kernels of rotlearn.geometry.eigen4 for one floating type; sym4.c includes this
 * file once for float and once for double, with REAL, UINT (the unsigned integer of REAL's
 * width), MANT (mantissa bits), BIAS (exponent bias) and NAME(x) (the suffixed name) defined.
 *
 * Layout: LANES matrices at a time, each entry of the block a row of LANES values (a[i][j][l]:
 * entry (i, j) of matrix l), so every step is a loop over the lanes that the compiler turns into
 * SIMD instructions; the block lives in the L1 cache from the load of its upper triangles to the
 * store of its eigenpairs. Only IEEE-exact operations (+ - * / sqrt, compare, select) on REAL, no
 * contraction into FMA (built with -ffp-contract=off): every lane computes the same rounded
 * numbers whatever the SIMD width, the block it falls in or the thread that runs it.
 */

typedef struct {
    REAL a[4][4][LANES]; /* upper triangle (i <= j) used; the diagonal ends as the eigenvalues */
    REAL v[4][4][LANES]; /* v[i][j]: component i of eigenvector j */
    REAL back[4][LANES]; /* the power-of-two factors that undo the two scalings, in pairs */
    REAL shift[LANES];   /* the mean diagonal, subtracted between the two scalings */
} NAME(block);

static INLINE REAL NAME(pow2)(INT k) { /* 2^k for 1 - BIAS <= k <= BIAS, exact */
    UINT bits = (UINT)(k + BIAS) << MANT;
    REAL x;
    memcpy(&x, &bits, sizeof x);
    return x;
}

static INLINE INT NAME(exponent)(REAL x) { /* the biased exponent field of x */
    UINT bits;
    memcpy(&bits, &x, sizeof bits);
    return (INT)((bits >> MANT) & ((((UINT)1) << (8 * sizeof(REAL) - 1 - MANT)) - 1));
}

static INLINE INT NAME(frexp_shift)(REAL m) {
    /* The k with m 2^k in [0.5, 1) for m > 0 (0 for m = 0; Inf/NaN give k < 1 - BIAS). */
    INT e = NAME(exponent)(m);
    INT e_big = NAME(exponent)(m * (REAL)18446744073709551616.0); /* 2^64: subnormal -> normal */
    INT k = e == 0 ? BIAS - 1 - e_big + 64 : BIAS - 1 - e;
    return m == 0 ? 0 : k;
}

/* Scale each matrix of the block by the power of two that puts its largest entry in [0.5, 1)
 * (exact: squares then neither overflow nor underflow); back0, back1 get the two factors that
 * undo it (for back1 first). */
static INLINE void NAME(scale)(NAME(block) *blk, REAL *back0, REAL *back1) {
    REAL m[LANES];
    for (int l = 0; l < LANES; ++l) m[l] = 0;
    for (int i = 0; i < 4; ++i)
        for (int j = i; j < 4; ++j)
            for (int l = 0; l < LANES; ++l) {
                REAL x = blk->a[i][j][l];
                x = x < 0 ? -x : x;
                m[l] = (x > m[l] || x != x) ? x : m[l];
            }
    for (int l = 0; l < LANES; ++l) {
        INT k = NAME(frexp_shift)(m[l]);
        /* k1 within [1 - BIAS, BIAS - 1], so that 2^-k1 too is a normal number (2^-BIAS is not:
         * pow2 would give 0 and every eigenvalue of a matrix with a subnormal largest entry 0) */
        INT k1 = k < 1 - BIAS ? 1 - BIAS : (k > BIAS - 1 ? BIAS - 1 : k);
        INT k2 = k > BIAS - 1 ? k - (BIAS - 1) : 0; /* > 0 only for a subnormal largest entry */
        REAL s1 = NAME(pow2)(k1), s2 = NAME(pow2)(k2);
        back0[l] = NAME(pow2)(-k1);
        back1[l] = NAME(pow2)(-k2);
        for (int i = 0; i < 4; ++i)
            for (int j = i; j < 4; ++j) blk->a[i][j][l] = blk->a[i][j][l] * s1 * s2;
    }
}

/* Load the upper triangles of matrices [start, start + count) (count <= LANES; the other lanes
 * get the zero matrix); scale each (`scale`), subtract its mean diagonal c = trace / 4 (no
 * overflow: the entries are below 4 now; the eigenvectors are those of A, the eigenvalues move
 * by c, and the rounding of the rotations is relative to the spread of the eigenvalues instead
 * of the largest entry), and scale again (a spread far below the largest entry would underflow
 * in the squares); V = I. */
static INLINE void NAME(load)(NAME(block) *blk, const REAL *A, int64_t start, int64_t count,
                              int64_t sb, int64_t sr, int64_t sc) {
    const REAL *base = A + start * sb;
    for (int i = 0; i < 4; ++i)
        for (int j = i; j < 4; ++j) {
            const REAL *entry = base + i * sr + j * sc;
            if (count == LANES)
                for (int l = 0; l < LANES; ++l) blk->a[i][j][l] = entry[l * sb];
            else
                for (int l = 0; l < LANES; ++l) blk->a[i][j][l] = l < count ? entry[l * sb] : 0;
        }
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j)
            for (int l = 0; l < LANES; ++l) blk->v[i][j][l] = (REAL)(i == j);
    NAME(scale)(blk, blk->back[0], blk->back[1]);
    for (int l = 0; l < LANES; ++l) {
        REAL c = ((blk->a[0][0][l] + blk->a[1][1][l]) + (blk->a[2][2][l] + blk->a[3][3][l]))
                 * (REAL)0.25;
        blk->shift[l] = c;
        for (int i = 0; i < 4; ++i) blk->a[i][i][l] = blk->a[i][i][l] - c;
    }
    NAME(scale)(blk, blk->back[2], blk->back[3]);
}

#define UP(i, j) blk->a[(i) < (j) ? (i) : (j)][(i) < (j) ? (j) : (i)]

/* One round: the rotations of the disjoint pairs (p1, q1) and (p2, q2) (p < q), each zeroing its
 * off-diagonal entry (tan t with |t| <= 1, the stable small-angle root), applied as A <- J^T A J
 * and V <- V J. With `last`, the off-diagonal entries (not read again) are left stale. */
static INLINE void NAME(round)(NAME(block) *blk, int p1, int q1,
                                                              int p2, int q2, int last,
                                                              REAL tiny) {
    for (int l = 0; l < LANES; ++l) {
        REAL c[2], t[2];
        const int p[2] = {p1, p2}, q[2] = {q1, q2};
        for (int r = 0; r < 2; ++r) {
            REAL app = blk->a[p[r]][p[r]][l], aqq = blk->a[q[r]][q[r]][l];
            REAL apq = blk->a[p[r]][q[r]][l];
            REAL d = aqq - app;
            REAL root = (REAL)SQRT(tiny + d * d + (REAL)4 * (apq * apq));
            REAL den = (d < 0 ? -root : root) + d; /* sign(d) (|d| + root), never 0 */
            t[r] = (REAL)2 * apq / den;
            c[r] = (REAL)1 / (REAL)SQRT((REAL)1 + t[r] * t[r]);
            blk->a[p[r]][p[r]][l] = app - t[r] * apq;
            blk->a[q[r]][q[r]][l] = aqq + t[r] * apq;
            if (!last) blk->a[p[r]][q[r]][l] = 0;
        }
        if (!last) { /* the 2x2 block coupling the pairs: rows by rotation 0, columns by 1 */
            REAL x11 = UP(p1, p2)[l], x12 = UP(p1, q2)[l];
            REAL x21 = UP(q1, p2)[l], x22 = UP(q1, q2)[l];
            REAL y11 = c[0] * (x11 - t[0] * x21), y21 = c[0] * (x21 + t[0] * x11);
            REAL y12 = c[0] * (x12 - t[0] * x22), y22 = c[0] * (x22 + t[0] * x12);
            UP(p1, p2)[l] = c[1] * (y11 - t[1] * y12);
            UP(p1, q2)[l] = c[1] * (y12 + t[1] * y11);
            UP(q1, p2)[l] = c[1] * (y21 - t[1] * y22);
            UP(q1, q2)[l] = c[1] * (y22 + t[1] * y21);
        }
        for (int i = 0; i < 4; ++i)
            for (int r = 0; r < 2; ++r) {
                REAL vp = blk->v[i][p[r]][l], vq = blk->v[i][q[r]][l];
                blk->v[i][p[r]][l] = c[r] * (vp - t[r] * vq);
                blk->v[i][q[r]][l] = c[r] * (vq + t[r] * vp);
            }
    }
}

#undef UP

static INLINE void NAME(jacobi)(NAME(block) *blk, int rounds) {
    const REAL tiny = TINY;
    /* `last` is a constant at each call site: no branch in the lane loops (AVX2 has no masked
     * stores, and a conditional store would keep the compiler from vectorising them). */
    for (int k = 0; k < rounds - 1; ++k) {
        switch (k % 3) { /* the three perfect matchings: one cyclic sweep per three rounds */
        case 0: NAME(round)(blk, 0, 1, 2, 3, 0, tiny); break;
        case 1: NAME(round)(blk, 0, 2, 1, 3, 0, tiny); break;
        default: NAME(round)(blk, 0, 3, 1, 2, 0, tiny); break;
        }
    }
    switch ((rounds - 1) % 3) {
    case 0: NAME(round)(blk, 0, 1, 2, 3, 1, tiny); break;
    case 1: NAME(round)(blk, 0, 2, 1, 3, 1, tiny); break;
    default: NAME(round)(blk, 0, 3, 1, 2, 1, tiny); break;
    }
}

/* Sort the eigenpairs (network (0,1)(2,3) | (0,2)(1,3) | (1,2) on the eigenvalues, ascending;
 * ties and NaN keep their order: only the column order is sorted, as a permutation per lane),
 * give column 0 the canonical sign (the first nonzero of w, x, y, z positive: quat_canonical's
 * rule), undo the second scaling, add the mean diagonal back, undo the first scaling, store. */
static INLINE void NAME(store)(const NAME(block) *blk, int64_t start, int64_t count, REAL *L,
                               REAL *q, REAL *V) {
    static const int network[5][2] = {{0, 1}, {2, 3}, {0, 2}, {1, 3}, {1, 2}};
    REAL lam[4][LANES];
    INT col[4][LANES];
    for (int j = 0; j < 4; ++j)
        for (int l = 0; l < LANES; ++l) {
            lam[j][l] = blk->a[j][j][l]; /* sorted before c is added (which can round to ties) */
            col[j][l] = j;
        }
    for (int k = 0; k < 5; ++k) {
        int a = network[k][0], b = network[k][1];
        for (int l = 0; l < LANES; ++l) {
            int swap = lam[a][l] > lam[b][l];
            REAL la = lam[a][l], lb = lam[b][l];
            INT ca = col[a][l], cb = col[b][l];
            lam[a][l] = swap ? lb : la;
            lam[b][l] = swap ? la : lb;
            col[a][l] = swap ? cb : ca;
            col[b][l] = swap ? ca : cb;
        }
    }
    for (int64_t l = 0; l < count; ++l) {
        int64_t b = start + l;
        INT c0 = col[0][l];
        REAL x = blk->v[0][c0][l], y = blk->v[1][c0][l], z = blk->v[2][c0][l];
        REAL w = blk->v[3][c0][l];
        /* sign(8 sign w + 4 sign x + 2 sign y + sign z), +1 for 0: each weight exceeds the sum
         * of the later ones, so the first nonzero component decides */
        int key = 8 * ((w > 0) - (w < 0)) + 4 * ((x > 0) - (x < 0)) + 2 * ((y > 0) - (y < 0))
                  + ((z > 0) - (z < 0));
        REAL s = key < 0 ? (REAL)-1 : (REAL)1;
        for (int j = 0; j < 4; ++j) {
            REAL x = lam[j][l] * blk->back[3][l] * blk->back[2][l] + blk->shift[l];
            L[4 * b + j] = x * blk->back[1][l] * blk->back[0][l];
        }
        for (int i = 0; i < 4; ++i) {
            REAL q_i = s * blk->v[i][c0][l];
            q[4 * b + i] = q_i;
            V[16 * b + 4 * i] = q_i;
            for (int j = 1; j < 4; ++j) V[16 * b + 4 * i + j] = blk->v[i][col[j][l]][l];
        }
    }
}

HOT static void NAME(forward_range)(const REAL *A, int64_t begin, int64_t end, int64_t sb,
                                int64_t sr, int64_t sc, int rounds, REAL *L, REAL *q, REAL *V) {
    NAME(block) blk;
    for (int64_t start = begin; start < end; start += LANES) {
        int64_t count = end - start < LANES ? end - start : LANES;
        NAME(load)(&blk, A, start, count, sb, sr, sc);
        NAME(jacobi)(&blk, rounds);
        NAME(store)(&blk, start, count, L, q, V);
    }
}

/* grad_A = sym(-u q^T + sum_i g_li v_i v_i^T), u = sum_{i>=1} v_i (v_i . g_q) / gap_i,
 * gap_i = max(l_i - l_0, gap_eps (l_3 - l_0)) (1 for l_0 = l_3: A = cI); sym(X) = (X + X^T) / 2,
 * exactly symmetric. gl / gq may be NULL (that output had no gradient). */
HOT static void NAME(backward_range)(const REAL *gl, const REAL *gq, const REAL *L, const REAL *V,
                                     REAL gap_eps, int64_t begin, int64_t end, REAL *G) {
    REAL lam[4][LANES], v[4][4][LANES], g_l[4][LANES], g_q[4][LANES], out[4][4][LANES];
    REAL clamp[LANES], coef[LANES], u[4][LANES];
    for (int j = 0; j < 4; ++j)
        for (int l = 0; l < LANES; ++l) {
            lam[j][l] = g_l[j][l] = g_q[j][l] = 0;
            for (int i = 0; i < 4; ++i) v[i][j][l] = 0;
        }
    for (int64_t start = begin; start < end; start += LANES) {
        int64_t count = end - start < LANES ? end - start : LANES;
        for (int64_t l = 0; l < count; ++l) { /* a last, partial block's other lanes: unused */
            int64_t b = start + l;
            for (int j = 0; j < 4; ++j) {
                lam[j][l] = L[4 * b + j];
                if (gl) g_l[j][l] = gl[4 * b + j];
                if (gq) g_q[j][l] = gq[4 * b + j];
                for (int i = 0; i < 4; ++i) v[i][j][l] = V[16 * b + 4 * i + j];
            }
        }
        for (int l = 0; l < LANES; ++l) {
            REAL spread = lam[3][l] - lam[0][l]; /* l4 - l1: as the gaps, free of A's trace */
            clamp[l] = (REAL)(spread == 0) + gap_eps * spread;
        }
        for (int i = 0; i < 4; ++i)
            for (int l = 0; l < LANES; ++l) u[i][l] = 0;
        for (int j = 1; j < 4; ++j) {
            for (int l = 0; l < LANES; ++l) {
                REAL gap = lam[j][l] - lam[0][l];
                gap = (gap > clamp[l] || gap != gap) ? gap : clamp[l];
                REAL dot = v[0][j][l] * g_q[0][l] + v[1][j][l] * g_q[1][l]
                           + v[2][j][l] * g_q[2][l] + v[3][j][l] * g_q[3][l];
                coef[l] = dot / gap;
            }
            for (int i = 0; i < 4; ++i)
                for (int l = 0; l < LANES; ++l) u[i][l] = u[i][l] + coef[l] * v[i][j][l];
        }
        for (int r = 0; r < 4; ++r)
            for (int c = r; c < 4; ++c)
                for (int l = 0; l < LANES; ++l) {
                    REAL x = g_l[0][l] * v[r][0][l] * v[c][0][l] + g_l[1][l] * v[r][1][l] * v[c][1][l]
                             + g_l[2][l] * v[r][2][l] * v[c][2][l] + g_l[3][l] * v[r][3][l] * v[c][3][l];
                    x = x - (REAL)0.5 * (u[r][l] * v[c][0][l] + u[c][l] * v[r][0][l]);
                    out[r][c][l] = x;
                    out[c][r][l] = x;
                }
        for (int64_t l = 0; l < count; ++l)
            for (int r = 0; r < 4; ++r)
                for (int c = 0; c < 4; ++c) G[16 * (start + l) + 4 * r + c] = out[r][c][l];
    }
}
