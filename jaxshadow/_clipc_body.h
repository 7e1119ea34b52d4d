/* The body of `_clipc.c`, included once per precision: REAL (double or float), SFX(name)
 * (the precision's suffix), EPS_D (the precision's machine epsilon, as a double), BIAS (its
 * exponent bias), SQRT, FREXP, LDEXP, FABS.
 *
 * One receiver at a time, `jaxshadow._clip_host.host_culled_codes` line by line: the same
 * formulas, evaluated in the same order and precision (each `np.sum` of three terms is
 * ((a0 + a1) + a2); a Python float constant meets an array in the array's precision, as NumPy's
 * weak scalars do: (REAL)(constant)). The comments name the NumPy helper each block mirrors. */

static inline REAL SFX(dot3)(const REAL *a, const REAL *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static inline void SFX(sub3)(const REAL *a, const REAL *b, REAL *out) {
    out[0] = a[0] - b[0];
    out[1] = a[1] - b[1];
    out[2] = a[2] - b[2];
}

static inline void SFX(cross3)(const REAL *a, const REAL *b, REAL *out) { /* _bsp._np_cross */
    REAL x = a[1] * b[2] - a[2] * b[1], y = a[2] * b[0] - a[0] * b[2], z = a[0] * b[1] - a[1] * b[0];
    out[0] = x;
    out[1] = y;
    out[2] = z;
}

static inline int SFX(differs)(const REAL *a, const REAL *b) { return a[0] != b[0] || a[1] != b[1] || a[2] != b[2]; }

static inline int SFX(nonzero)(const REAL *a) { return a[0] != 0 || a[1] != 0 || a[2] != 0; }

/* np.max of |x| (NaN propagates, as np.max does). */
static inline REAL SFX(absmax)(const REAL *x, int n) {
    REAL m = FABS(x[0]);
    for (int i = 1; i < n; i++) {
        REAL a = FABS(x[i]);
        if (a > m || a != a) m = a;
        if (m != m) return m;
    }
    return m;
}

static void SFX(newell)(const REAL *v, int k, REAL *out) { /* _bsp._newell_np */
    REAL c[3];
    SFX(cross3)(v, v + 3 * (1 % k), out);
    for (int i = 1; i < k; i++) {
        SFX(cross3)(v + 3 * i, v + 3 * ((i + 1) % k), c);
        out[0] += c[0];
        out[1] += c[1];
        out[2] += c[2];
    }
}

static inline REAL SFX(pow2_scale)(REAL mag) { /* _np_pow2_scale */
    int ok = mag > 0 && isfinite(mag), e;
    (void)FREXP(ok ? mag : (REAL)1, &e);
    int k = -e;
    if (k < 2 - BIAS) k = 2 - BIAS;
    if (k > BIAS - 1) k = BIAS - 1;
    return LDEXP((REAL)1, k);
}

static inline void SFX(rescale3)(REAL *x) { /* _np_rescale_rows, one row */
    REAL s = SFX(pow2_scale)(SFX(absmax)(x, 3));
    x[0] *= s;
    x[1] *= s;
    x[2] *= s;
}

static inline void SFX(safe_normalize)(const REAL *x, REAL *out) {
    REAL sq = x[0] * x[0] + x[1] * x[1] + x[2] * x[2];
    if (sq > 0) {
        REAL r = SQRT(sq);
        out[0] = x[0] / r;
        out[1] = x[1] / r;
        out[2] = x[2] / r;
    } else {
        out[0] = out[1] = out[2] = 0;
    }
}

static inline REAL SFX(safe_div)(REAL num, REAL den) { return den != 0 ? num / den : (REAL)0; }

/* _np_edge_planes: the plane through p and each edge v_i -> v_{i+1} (zero for a padding edge). */
static void SFX(edge_planes)(const REAL *p, const REAL *v, int k, REAL *out) {
    REAL a[3], b[3];
    for (int i = 0; i < k; i++) {
        const REAL *vi = v + 3 * i, *vn = v + 3 * ((i + 1) % k);
        if (SFX(differs)(vn, vi)) {
            SFX(sub3)(vn, p, a);
            SFX(sub3)(vi, p, b);
            SFX(cross3)(a, b, out + 3 * i);
        } else {
            out[3 * i] = out[3 * i + 1] = out[3 * i + 2] = 0;
        }
    }
}

/* _np_horizon_clip_edges with _np_clip_recipes: polygon `v (k, 3)` clipped to the half-space
 * (x - q).h >= 0; its k + 1 starts and ends (points and recipes). Returns `bad`. */
static int SFX(horizon_clip)(const REAL *q, const REAL *h, const REAL *v, int k, REAL *starts, REAL *ends,
                             int64_t *s_a, int64_t *s_b, uint8_t *s_i, int64_t *e_a, int64_t *e_b, uint8_t *e_i) {
    REAL da[k], db[k], x[k][3], r[3];
    int n_exit = 0, n_enter = 0, ix = 0, ie = 0;
    for (int i = 0; i < k; i++) {
        const REAL *vi = v + 3 * i, *vn = v + 3 * ((i + 1) % k);
        SFX(sub3)(vi, q, r);
        da[i] = SFX(dot3)(r, h);
        SFX(sub3)(vn, q, r);
        db[i] = SFX(dot3)(r, h);
    }
    for (int i = 0; i < k; i++) {
        const REAL *vi = v + 3 * i, *vn = v + 3 * ((i + 1) % k);
        int a_in = da[i] >= 0, b_in = db[i] >= 0;
        int exiting = a_in && !b_in, entering = !a_in && b_in;
        if (exiting && n_exit++ == 0) ix = i;
        if (entering && n_enter++ == 0) ie = i;
        int crossing = a_in != b_in;
        REAL den = crossing ? da[i] - db[i] : (REAL)1;
        REAL t = crossing ? da[i] / den : (REAL)0;
        for (int c = 0; c < 3; c++) x[i][c] = vi[c] + t * (vn[c] - vi[c]);
        s_a[i] = i;
        s_b[i] = (i + 1) % k;
        s_i[i] = (uint8_t)entering;
        e_a[i] = b_in ? (i + 1) % k : i;
        e_b[i] = (i + 1) % k;
        e_i[i] = (uint8_t)exiting;
    }
    int any_cut = n_exit > 0 && n_enter > 0;
    s_a[k] = any_cut ? ix : 0;
    s_b[k] = (ix + 1) % k;
    s_i[k] = (uint8_t)any_cut;
    e_a[k] = any_cut ? ie : 0;
    e_b[k] = (ie + 1) % k;
    e_i[k] = (uint8_t)any_cut;
    for (int i = 0; i <= k; i++) {
        const REAL *ps = s_i[i] ? x[s_a[i]] : v + 3 * s_a[i];
        const REAL *pe = e_i[i] ? x[e_a[i]] : v + 3 * e_a[i];
        for (int c = 0; c < 3; c++) {
            starts[3 * i + c] = ps[c];
            ends[3 * i + c] = pe[c];
        }
    }
    return n_exit > 1 || n_enter > 1;
}

static inline void SFX(project)(const REAL *p, const REAL *x, const REAL *ne, REAL hp, REAL *out) { /* _np_project */
    REAL r[3];
    SFX(sub3)(x, p, r);
    REAL w = -SFX(dot3)(r, ne);
    REAL scale = w > 0 ? hp / w : (REAL)0;
    for (int c = 0; c < 3; c++) out[c] = p[c] + scale * r[c];
}

static inline void SFX(crossing_point)(const REAL *p, const REAL *c_in, const REAL *ne, REAL hp, REAL *out) {
    REAL c[3] = {c_in[0], c_in[1], c_in[2]};
    SFX(rescale3)(c);
    REAL den = -SFX(dot3)(c, ne);
    int ok = FABS(den) > (REAL)(EPS_D * EPS_D) * SFX(absmax)(c, 3) * SFX(absmax)(ne, 3);
    REAL t = ok ? hp / den : (REAL)0;
    for (int k = 0; k < 3; k++) out[k] = p[k] + c[k] * t;
}

/* _np_relevance for one receiver: relevant[m] for the m occluders `o (m, ko, 3)`. */
static void SFX(relevance)(const REAL *p, const REAL *n, const REAL *v, int k, const REAL *o, int m, int ko,
                           int closed, uint8_t *relevant) {
    const REAL tol = (REAL)(COLLINEAR_EPS * EPS_D), ntol = (REAL)(-(COLLINEAR_EPS * EPS_D));
    const REAL *e0 = v;
    REAL ne[3], t[3], planes[k + 1][3], pnorm[k + 1], rel[ko][3], rnorm[ko], no[3], dp[3];
    SFX(newell)(v, k, ne);
    SFX(sub3)(p, e0, t);
    int in_front = SFX(dot3)(ne, t) > 0;
    SFX(edge_planes)(p, v, k, &planes[0][0]);
    for (int c = 0; c < 3; c++) planes[k][c] = n[c];
    for (int i = 0; i <= k; i++) pnorm[i] = SQRT(SFX(dot3)(planes[i], planes[i]));
    const REAL ne_norm = SQRT(SFX(dot3)(ne, ne));
    for (int j = 0; j < m; j++) {
        const REAL *oj = o + (size_t)3 * ko * j;
        for (int i = 0; i < ko; i++) {
            SFX(sub3)(oj + 3 * i, p, rel[i]);
            rnorm[i] = SQRT(SFX(dot3)(rel[i], rel[i]));
        }
        int cut_by_cone = 0;
        for (int c = 0; c <= k && !cut_by_cone; c++) {
            if (!(pnorm[c] > 0)) continue;
            int out_cone = 1;
            for (int i = 0; i < ko && out_cone; i++) out_cone = SFX(dot3)(rel[i], planes[c]) < ntol * (pnorm[c] * rnorm[i]);
            cut_by_cone = out_cone;
        }
        int behind = 1;
        for (int i = 0; i < ko && behind; i++) {
            SFX(sub3)(oj + 3 * i, e0, t);
            behind = SFX(dot3)(t, ne) < ntol * (ne_norm * SQRT(SFX(dot3)(t, t)));
        }
        SFX(newell)(oj, ko, no);
        REAL nn = SQRT(SFX(dot3)(no, no));
        SFX(sub3)(p, oj, dp);
        REAL d_p = SFX(dot3)(dp, no), s_p = nn * SQRT(SFX(dot3)(dp, dp));
        int all_pos = 1, all_neg = 1;
        for (int i = 0; i < k; i++) {
            SFX(sub3)(v + 3 * i, oj, t);
            REAL d_v = SFX(dot3)(t, no), s_v = nn * SQRT(SFX(dot3)(t, t));
            all_pos = all_pos && d_v > tol * s_v;
            all_neg = all_neg && d_v < ntol * s_v;
        }
        int one_side = ((d_p > tol * s_p && all_pos) || (d_p < ntol * s_p && all_neg)) && nn > 0;
        int irrelevant = cut_by_cone || behind || one_side || (closed && d_p < ntol * s_p);
        relevant[j] = (uint8_t)(in_front && !irrelevant);
    }
}

/* _codes_shadowed for one receiver with `a_occ` selected occluders `occ (a_occ, ko, 3)` (the
 * dummies zero): the slot codes `out_sc`, `out_ec (cap)`, `used (cap)`, the selected
 * occluders' table recipes (written into rec_a/b/i at t_ps..t_e0) and `*count`; returns bad. */
static int SFX(codes_shadowed)(const REAL *p, const REAL *n, const REAL *v, int k, const REAL *occ, int a_occ, int ko,
                               const REAL *e_starts, const REAL *e_ends, int cap, int64_t *out_sc, int64_t *out_ec,
                               int32_t *used, int64_t *count_out, int64_t *rec_a, int64_t *rec_b, uint8_t *rec_i) {
    const int k1 = k + 1, kq = ko + 1, n_reg = a_occ + 1;
    const int n_planes = k1 > kq ? k1 : kq, n_pl = n_reg * n_planes;
    const int t_ps = 2 * k1, t_pe = t_ps + a_occ * kq, t_e0 = t_ps + 2 * a_occ * kq, n_table = t_e0 + 1;
    const int n_cand = k1 + a_occ * kq, n_tab = 2 * n_cand;
    const REAL tol2 = (REAL)((COLLINEAR_EPS * EPS_D) * (COLLINEAR_EPS * EPS_D));
    const REAL *e0 = v;
    REAL ne[3], t3[3], hp;

    /* _clip._candidates: the emitter frame. */
    SFX(newell)(v, k, ne);
    SFX(sub3)(p, e0, t3);
    hp = SFX(dot3)(ne, t3);
    {
        REAL e_scale = SFX(pow2_scale)(SFX(absmax)(ne, 3));
        for (int c = 0; c < 3; c++) ne[c] *= e_scale;
        hp *= e_scale;
    }
    REAL e_normals[k1][3];
    SFX(edge_planes)(p, v, k, &e_normals[0][0]);
    for (int c = 0; c < 3; c++) e_normals[k][c] = n[c];
    for (int i = 0; i < k1; i++) SFX(rescale3)(e_normals[i]);

    /* _clip._occluder_sides / _occluder_regions, and the occluders clipped to the emitter plane. */
    REAL o_normals[a_occ][kq][3], o_s[a_occ][kq][3], o_e[a_occ][kq][3], s_sign[a_occ];
    uint8_t active[a_occ];
    int bad = 0;
    for (int a = 0; a < a_occ; a++) {
        const REAL *oa = occ + (size_t)3 * ko * a;
        REAL rel[ko][3], no[3], bound_no[3] = {0, 0, 0}, h[ko], err[ko];
        for (int j = 0; j < ko; j++) SFX(sub3)(oa + 3 * j, p, rel[j]);
        REAL sigma = SFX(pow2_scale)(SFX(absmax)(&rel[0][0], 3 * ko));
        for (int j = 0; j < ko; j++)
            for (int c = 0; c < 3; c++) rel[j][c] *= sigma;
        SFX(newell)(&rel[0][0], ko, no);
        for (int j = 0; j < ko; j++) {
            REAL x[3], y[3];
            const REAL *nx = rel[(j + 1) % ko];
            for (int c = 0; c < 3; c++) {
                x[c] = FABS(rel[j][c]);
                y[c] = FABS(nx[c]);
            }
            REAL ac[3] = {x[1] * y[2] + x[2] * y[1], x[2] * y[0] + x[0] * y[2], x[0] * y[1] + x[1] * y[0]};
            if (j == 0) {
                for (int c = 0; c < 3; c++) bound_no[c] = ac[c];
            } else {
                for (int c = 0; c < 3; c++) bound_no[c] += ac[c];
            }
        }
        for (int j = 0; j < ko; j++) {
            REAL ar[3] = {FABS(rel[j][0]), FABS(rel[j][1]), FABS(rel[j][2])};
            h[j] = SFX(dot3)(no, rel[j]);
            err[j] = SFX(dot3)(bound_no, ar);
        }
        const REAL cb = (REAL)((double)(ko + 8) / 2.0 * EPS_D);
        REAL d_o = h[0];
        REAL s = d_o < 0 ? (REAL)1 : (REAL)-1;
        s_sign[a] = s;
        int act = 1;
        for (int j = 0; j < ko; j++) act = act && (-s * h[j] > cb * err[j]);
        active[a] = (uint8_t)act;
        for (int j = 0; j < ko; j++) {
            const REAL *oj = oa + 3 * j, *on = oa + 3 * ((j + 1) % ko);
            if (SFX(differs)(on, oj)) {
                SFX(cross3)(rel[(j + 1) % ko], rel[j], o_normals[a][j]);
                for (int c = 0; c < 3; c++) o_normals[a][j][c] = s * o_normals[a][j][c];
            } else {
                for (int c = 0; c < 3; c++) o_normals[a][j][c] = s * (REAL)0;
            }
            SFX(rescale3)(o_normals[a][j]);
        }
        REAL coef = hp * sigma * -s, ad = FABS(d_o);
        for (int c = 0; c < 3; c++) o_normals[a][ko][c] = coef * no[c] + ad * ne[c];
        SFX(rescale3)(o_normals[a][ko]);
        /* The selected occluder's edges clipped to the lit side of the emitter plane; their recipes. */
        int64_t os_a[kq], os_b[kq], oe_a[kq], oe_b[kq];
        uint8_t os_i[kq], oe_i[kq];
        bad |= SFX(horizon_clip)(e0, ne, oa, ko, &o_s[a][0][0], &o_e[a][0][0], os_a, os_b, os_i, oe_a, oe_b, oe_i);
        const int64_t base = k + (int64_t)ko * a;
        for (int j = 0; j < kq; j++) {
            int u = t_ps + a * kq + j, w = t_pe + a * kq + j;
            rec_a[u] = os_a[j] + base;
            rec_b[u] = os_b[j] + base;
            rec_i[u] = os_i[j];
            rec_a[w] = oe_a[j] + base;
            rec_b[w] = oe_b[j] + base;
            rec_i[w] = oe_i[j];
        }
    }

    /* Candidates: the light's clipped edges, then every occluder edge clipped to the cone
     * (p, E_h) by Cyrus-Beck (_clip._cyrus_beck) and projected onto the emitter plane. */
    REAL starts[n_cand][3], ends[n_cand][3], own[n_cand][3];
    int64_t cand_start[n_cand], cand_end[n_cand], own_id[n_cand], region[n_cand];
    REAL sig[n_cand];
    for (int c = 0; c < k1; c++) {
        for (int x = 0; x < 3; x++) {
            starts[c][x] = e_starts[3 * c + x];
            ends[c][x] = e_ends[3 * c + x];
            own[c][x] = e_normals[c][x];
        }
        cand_start[c] = c;
        cand_end[c] = k1 + c;
        own_id[c] = c;
        region[c] = 0;
        sig[c] = 1;
    }
    for (int a = 0; a < a_occ; a++) {
        for (int j = 0; j < kq; j++) {
            REAL g0[k1], g1[k1], r0[3], dd[3];
            SFX(sub3)(o_s[a][j], p, r0);
            SFX(sub3)(o_e[a][j], o_s[a][j], dd);
            int nc = 1, i0 = 0, i1 = 0;
            REAL best_lo = 0, best_hi = 0;
            for (int c = 0; c < k1; c++) {
                g0[c] = SFX(dot3)(r0, e_normals[c]);
                g1[c] = SFX(dot3)(dd, e_normals[c]);
                REAL tc = SFX(safe_div)(-g0[c], g1[c]);
                REAL lo = g1[c] > 0 ? tc : (REAL)0, hi = g1[c] < 0 ? tc : (REAL)1;
                /* np.argmax / np.argmin: the first extremum; a NaN is the extremum (the first one). */
                if (c == 0 || (best_lo == best_lo && (lo > best_lo || lo != lo))) {
                    best_lo = lo;
                    i0 = c;
                }
                if (c == 0 || (best_hi == best_hi && (hi < best_hi || hi != hi))) {
                    best_hi = hi;
                    i1 = c;
                }
                nc = nc && (g1[c] != 0 || g0[c] >= 0);
            }
            REAL t0 = best_lo > 0 ? best_lo : (REAL)0, t1 = best_hi < 1 ? best_hi : (REAL)1;
            if (best_lo != best_lo) t0 = best_lo;
            if (best_hi != best_hi) t1 = best_hi;
            int ok = nc && t1 > t0 && active[a];
            REAL cr[3], x0[3], x1[3], pr_s[3], pr_e[3], a2[3], b2[3];
            SFX(cross3)(e_normals[i0], o_normals[a][j], cr);
            SFX(crossing_point)(p, cr, ne, hp, x0);
            SFX(cross3)(e_normals[i1], o_normals[a][j], cr);
            SFX(crossing_point)(p, cr, ne, hp, x1);
            SFX(project)(p, o_s[a][j], ne, hp, pr_s);
            SFX(project)(p, o_e[a][j], ne, hp, pr_e);
            const int u = a * kq + j, plane_q = (1 + a) * n_planes + j;
            int64_t cross0 = n_table + (int64_t)i0 * n_pl + plane_q, cross1 = n_table + (int64_t)i1 * n_pl + plane_q;
            int64_t a_code = ok ? (t0 > 0 ? cross0 : t_ps + u) : t_e0;
            int64_t b_code = ok ? (t1 < 1 ? cross1 : t_pe + u) : t_e0;
            for (int x = 0; x < 3; x++) {
                a2[x] = ok ? (t0 > 0 ? x0[x] : pr_s[x]) : e0[x];
                b2[x] = ok ? (t1 < 1 ? x1[x] : pr_e[x]) : e0[x];
            }
            int ccw = s_sign[a] > 0, c = k1 + u;
            for (int x = 0; x < 3; x++) {
                starts[c][x] = ccw ? b2[x] : a2[x];
                ends[c][x] = ccw ? a2[x] : b2[x];
                own[c][x] = o_normals[a][j][x];
            }
            cand_start[c] = ccw ? b_code : a_code;
            cand_end[c] = ccw ? a_code : b_code;
            own_id[c] = plane_q;
            region[c] = a + 1;
            sig[c] = -1;
        }
    }

    /* The regions' planes (zero-padded to n_planes), which are valid, their unit normals. */
    REAL planes[n_reg][n_planes][3], un[n_reg][n_planes][3];
    uint8_t reg_valid[n_reg][n_planes], reg_active[n_reg];
    reg_active[0] = 1;
    for (int a = 0; a < a_occ; a++) reg_active[a + 1] = active[a];
    for (int r = 0; r < n_reg; r++) {
        int kr = r == 0 ? k1 : kq;
        for (int q = 0; q < n_planes; q++) {
            for (int x = 0; x < 3; x++) planes[r][q][x] = q < kr ? (r == 0 ? e_normals[q][x] : o_normals[r - 1][q][x]) : (REAL)0;
            reg_valid[r][q] = (uint8_t)(SFX(nonzero)(planes[r][q]) && reg_active[r]);
            SFX(safe_normalize)(planes[r][q], un[r][q]);
        }
    }
    const int in_front = hp > 0;

    /* _clip.edge_breakpoints / _interval_on_region / _boundary_runs, candidate by candidate;
     * the runs in (candidate, run) order, as the device's flattened (C, R) table. */
    const int n_ts = 2 + 2 * n_reg, n_pieces = n_ts - 1;
    int64_t run_sc[n_cand * n_reg], run_ec[n_cand * n_reg];
    uint8_t run_valid[n_cand * n_reg];
    for (int c = 0; c < n_cand; c++) {
        REAL d[3], rs[3], uo[3];
        REAL lo[n_reg], hi[n_reg];
        int64_t i_lo[n_reg], i_hi[n_reg];
        uint8_t c_nc[n_reg], c_c[n_reg], any_c[n_reg];
        SFX(sub3)(ends[c], starts[c], d);
        SFX(sub3)(starts[c], p, rs);
        SFX(safe_normalize)(own[c], uo);
        for (int r = 0; r < n_reg; r++) {
            if (!reg_active[r]) { /* no valid plane: what the loop below gives, without it */
                lo[r] = (REAL)-INFINITY;
                hi[r] = (REAL)INFINITY;
                i_lo[r] = i_hi[r] = 0;
                c_nc[r] = c_c[r] = 1;
                any_c[r] = 0;
                continue;
            }
            int nc = 1, cc = 1, ac = 0;
            int64_t il = 0, ih = 0;
            REAL bl = 0, bh = 0;
            for (int q = 0; q < n_planes; q++) {
                const REAL *pl = planes[r][q], *u = un[r][q];
                REAL g0 = rs[0] * pl[0] + rs[1] * pl[1] + rs[2] * pl[2];
                REAL g1 = d[0] * pl[0] + d[1] * pl[1] + d[2] * pl[2];
                REAL c1 = uo[1] * u[2] - uo[2] * u[1], c2 = uo[2] * u[0] - uo[0] * u[2], c3 = uo[0] * u[1] - uo[1] * u[0];
                int valid = reg_valid[r][q];
                int collinear = valid && (c1 * c1 + c2 * c2 + c3 * c3 <= tol2);
                int side_ok = sig[c] * (u[0] * uo[0] + u[1] * uo[1] + u[2] * uo[2]) > 0;
                int generic = valid && !collinear;
                REAL tcr = SFX(safe_div)(-g0, g1);
                REAL tl = generic && g1 > 0 ? tcr : (REAL)-INFINITY;
                REAL th = generic && g1 < 0 ? tcr : (REAL)INFINITY;
                if (q == 0 || tl > bl) {
                    bl = tl;
                    il = q;
                }
                if (q == 0 || th < bh) {
                    bh = th;
                    ih = q;
                }
                nc = nc && (!generic || g1 != 0 || g0 >= 0);
                cc = cc && (!collinear || side_ok);
                ac = ac || collinear;
            }
            lo[r] = bl;
            hi[r] = bh;
            i_lo[r] = il;
            i_hi[r] = ih;
            c_nc[r] = (uint8_t)nc;
            c_c[r] = (uint8_t)cc;
            any_c[r] = (uint8_t)ac;
        }
        /* The breakpoints: 0, 1, then every other region's interval ends; sorted stably. */
        REAL ts[n_ts];
        int64_t codes[n_ts];
        ts[0] = 0;
        ts[1] = 1;
        codes[0] = c;
        codes[1] = n_cand + c;
        for (int h = 0; h < 2; h++) {
            for (int r = 0; r < n_reg; r++) {
                int other = r != region[c];
                REAL cut = other ? (h == 0 ? lo[r] : hi[r]) : (REAL)0;
                int64_t id = (int64_t)r * n_planes + (h == 0 ? i_lo[r] : i_hi[r]);
                int64_t mn = own_id[c] < id ? own_id[c] : id, mx = own_id[c] < id ? id : own_id[c];
                int64_t code = cut <= 0 ? (int64_t)c : (cut >= 1 ? (int64_t)(n_cand + c) : n_tab + mn * n_pl + mx);
                REAL tv = cut < 0 ? (REAL)0 : (cut > 1 ? (REAL)1 : cut); /* np.clip */
                ts[2 + h * n_reg + r] = tv;
                codes[2 + h * n_reg + r] = code;
            }
        }
        for (int i = 1; i < n_ts; i++) { /* stable insertion sort */
            REAL tv = ts[i];
            int64_t cv = codes[i];
            int j = i - 1;
            while (j >= 0 && ts[j] > tv) {
                ts[j + 1] = ts[j];
                codes[j + 1] = codes[j];
                j--;
            }
            ts[j + 1] = tv;
            codes[j + 1] = cv;
        }
        uint8_t free_[n_pieces], last[n_pieces], keep[n_pieces];
        int64_t run_end[n_pieces];
        for (int i = 0; i < n_pieces; i++) {
            REAL tm = (REAL)0.5 * (ts[i] + ts[i + 1]);
            int blocked = 0;
            for (int r = 0; r < n_reg && !blocked; r++) {
                if (r == region[c]) continue;
                int inside = lo[r] < tm && tm < hi[r];
                int member = inside && c_nc[r] && c_c[r] && reg_active[r];
                int tie = inside && c_nc[r] && any_c[r] && r < region[c];
                blocked = (member && r > 0) || tie;
            }
            free_[i] = (uint8_t)!blocked;
        }
        for (int i = 0; i < n_pieces; i++) last[i] = (uint8_t)(i == n_pieces - 1 || !free_[i + 1]);
        int64_t re = n_pieces - 1;
        for (int i = n_pieces - 1; i >= 0; i--) {
            int64_t val = last[i] ? i : n_pieces - 1;
            if (val < re) re = val;
            run_end[i] = re;
        }
        int n_keep = 0;
        for (int i = 0; i < n_pieces; i++) {
            int begins = free_[i] && (i == 0 || !free_[i - 1]);
            keep[i] = (uint8_t)(begins && ts[run_end[i] + 1] > ts[i]);
        }
        for (int r = 0; r < n_reg; r++) {
            run_sc[c * n_reg + r] = codes[0];
            run_ec[c * n_reg + r] = codes[run_end[0] + 1];
            run_valid[c * n_reg + r] = 0;
        }
        for (int i = 0; i < n_pieces; i++) {
            if (!keep[i]) continue;
            if (n_keep < n_reg) {
                run_sc[c * n_reg + n_keep] = codes[i];
                run_ec[c * n_reg + n_keep] = codes[run_end[i] + 1];
                run_valid[c * n_reg + n_keep] = (uint8_t)in_front;
            }
            n_keep++;
        }
    }

    /* Compaction (visible_edges_compact) and the codes -> the device table's. */
    int64_t count = 0;
    for (int i = 0; i < n_cand * n_reg; i++) {
        if (!run_valid[i]) continue;
        if (count < cap) {
            int64_t sc = run_sc[i], ec = run_ec[i];
            out_sc[count] = sc < n_cand ? cand_start[sc] : (sc < n_tab ? cand_end[sc - n_cand] : sc - n_tab + n_table);
            out_ec[count] = ec < n_cand ? cand_start[ec] : (ec < n_tab ? cand_end[ec - n_cand] : ec - n_tab + n_table);
            used[count] = 1;
        }
        count++;
    }
    for (int64_t s = count; s < cap; s++) {
        out_sc[s] = t_e0;
        out_ec[s] = t_e0;
        used[s] = 0;
    }
    *count_out = count;
    return bad;
}

/* host_culled_codes for one receiver. */
static void SFX(receiver)(const REAL *p, const REAL *n, const REAL *v, int k, const REAL *occ_all, int m, int ko,
                          int a_max, int cap, int closed, int32_t *idx, int32_t *kind, int32_t *ra, int32_t *rb,
                          int32_t *ri, int32_t *used, int32_t *overflow) {
    const int k1 = k + 1, kq = ko + 1;
    const int t_ps = 2 * k1, t_pe = t_ps + a_max * kq, t_e0 = t_pe + a_max * kq, n_table = t_e0 + 1;
    const int n_planes = k1 > kq ? k1 : kq, n_pl = (a_max + 1) * n_planes;
    uint8_t relevant[m > 0 ? m : 1];
    SFX(relevance)(p, n, v, k, occ_all, m, ko, closed, relevant);
    int count_sel = 0;
    for (int j = 0; j < m; j++) {
        if (!relevant[j]) continue;
        if (count_sel < a_max) idx[count_sel] = j;
        count_sel++;
    }
    for (int a = count_sel; a < a_max; a++) idx[a] = m;
    REAL occ[a_max > 0 ? a_max : 1][ko][3];
    for (int a = 0; a < a_max; a++)
        for (int j = 0; j < ko; j++)
            for (int x = 0; x < 3; x++) occ[a][j][x] = idx[a] < m ? occ_all[((size_t)idx[a] * ko + j) * 3 + x] : (REAL)0;

    REAL ne[3], t3[3];
    SFX(newell)(v, k, ne);
    SFX(sub3)(p, v, t3);
    const int in_front = SFX(dot3)(ne, t3) > 0;
    int64_t out_sc[cap], out_ec[cap], count = 0;
    int64_t rec_a[n_table], rec_b[n_table];
    uint8_t rec_i[n_table];
    for (int i = 0; i < n_table; i++) {
        rec_a[i] = rec_b[i] = 0;
        rec_i[i] = 0;
    }
    REAL e_starts[k1][3], e_ends[k1][3];
    int bad = SFX(horizon_clip)(p, n, v, k, &e_starts[0][0], &e_ends[0][0], rec_a, rec_b, rec_i, rec_a + k1, rec_b + k1,
                                rec_i + k1);
    if (count_sel == 0) {
        for (int s = 0; s < cap; s++) {
            out_sc[s] = s < k1 ? s : t_e0;
            out_ec[s] = s < k1 ? k1 + s : t_e0;
            used[s] = s < k1 && in_front;
        }
    } else {
        bad |= SFX(codes_shadowed)(p, n, v, k, &occ[0][0][0], a_max, ko, &e_starts[0][0], &e_ends[0][0], cap, out_sc,
                                   out_ec, used, &count, rec_a, rec_b, rec_i);
    }
    for (int s = 0; s < 2 * cap; s++) {
        int64_t code = s < cap ? out_sc[s] : out_ec[s - cap];
        if (code < n_table) {
            kind[s] = (code >= t_ps && code < t_e0) ? 1 : 0;
            ra[s] = (int32_t)rec_a[code];
            rb[s] = (int32_t)rec_b[code];
            ri[s] = rec_i[code];
        } else {
            int64_t kk = code - n_table;
            kind[s] = 2;
            ra[s] = (int32_t)(kk / n_pl);
            rb[s] = (int32_t)(kk % n_pl);
            ri[s] = 0;
        }
    }
    *overflow = count_sel > a_max || count > cap || bad;
}

/* The batch, packed as `_clip_host.culled_visible_edges_host`'s callback exchanges it: each of
 * the `b` rows of `x` is `[p (3) | n (3) | verts (k, 3) | occluders (m, ko, 3)]`, each row of
 * `out` is `[idx (a_max) | kind, a, b, interp (2 cap each) | used (cap) | overflow (1)]`.
 * Returns 0, or 1 for sizes it cannot take. */
int SFX(jaxshadow_host_codes)(int64_t b, int k, int m, int ko, int a_max, int cap, int closed, const REAL *x,
                              int32_t *out) {
    if (k < 1 || ko < 1 || m < 0 || a_max < 1 || cap < k + 1) return 1;
    const size_t in_w = 6 + 3 * (size_t)k + 3 * (size_t)m * ko, out_w = (size_t)a_max + 9 * (size_t)cap + 1;
    for (int64_t i = 0; i < b; i++) {
        const REAL *row = x + in_w * i;
        int32_t *o = out + out_w * i, *kind = o + a_max;
        SFX(receiver)(row, row + 3, row + 6, k, row + 6 + 3 * k, m, ko, a_max, cap, closed, o, kind, kind + 2 * cap,
                      kind + 4 * cap, kind + 6 * cap, kind + 8 * cap, kind + 9 * cap);
    }
    return 0;
}
