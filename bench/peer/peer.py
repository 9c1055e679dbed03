#!/usr/bin/env python3
"""The numpy/scipy peer of tofwave's pipeline, written to be fast: whole
batches of frames as 2-D arrays, every stage vectorised over the frames.

Used only by `tofwave bench`, which writes the frames (raw little-endian i16
codes, one file per channel, frames one after another) and a JSON header,
runs this script in the same invocation, and compares ranges and time per
frame. Two modes (the header's "mode"):

* "full" mirrors, stage for stage, what tofwave's reference configuration
  (ML timing, events on) computes per frame:
  start  decode the start channel; its peak; mean and sigma off the pulse;
         the start-template matched filter around the peak; parabolic peak;
         Gauss-Newton ML fit (amplitude, delay) of the start shape; the
         shape-mismatch chi^2 at 17 quarter-sample positions; t_ref.
  noise  decode the stop channel; range and noise gates from t_ref; gate
         mean, sigma, skewness, excess kurtosis; Jarque-Bera p-value; robust
         sigma (probit fit of the codes' histogram, tofwave's estimator for
         quantised samples); the contamination test.
  detect noise colour: gate autocovariance at lags 0..T-1 (T = template
         length) by FFT, pooled over all frames so far; the filter output's
         variance gain and lag-1 correlation from it; the Student-t
         threshold with the gate's mean-error inflation; matched filter over
         the whole frame (FFT with the template's spectrum computed once);
         local maxima above the threshold in the range gate; noise-gate
         up-crossings of the previous frame's threshold, cumulative, with
         Clopper-Pearson 95 % and 99.8 % intervals.
  resolve successive cancellation: Gauss-Newton ML fit (amplitude, delay)
         of the strongest peak, pulse subtracted, the matched filter output
         updated where the pulse reaches, next peak above the threshold,
         ... (at most 32); misfit (residual RMS / sigma) of each pulse.
  events band-subspace energy of whole noise-gate windows (the learned
         null: scaled chi^2 from the quartiles of the last 2048 windows,
         refitted every 64 new windows); for each return, the energy the
         band subspace explains beyond the pulse and its slope in the
         return's window, against the null's limit; where above it, the
         matched-subspace z of the pulse projected off the band (event or
         return with event).
  timing t_stop at the fit's fraction point, Cramer-Rao sigma, range and
         range sigma (start sigma included), SNR, probability of detection.
* "minimal": stop channel only: decode; noise-gate mean and sigma; matched
  filter; threshold; strongest peak in the range gate; parabolic peak;
  Gauss-Newton ML fit of the delay; t_stop.

usage: peer.py HEADER.json OUT.json
"""

import json
import sys
import time

import numpy as np
import scipy
import scipy.fft as sfft
from scipy import special, stats

# Frames per batch. Measured on the reference frames (2 cores, loaded): one
# full-frame correlation costs 19-27 us/frame with scipy.fft and the
# template's spectrum computed once (batches of 64-512), against 42 for
# signal.fftconvolve on 2000 frames at once, 55 for oaconvolve, 82 for
# ndimage.correlate1d and 86 for a sliding-window matrix product; the whole
# stage-matched peer ran 275 us/frame at 64 frames a batch, 256 at 128.
BATCH = 128


class Shape:
    """Bigaussian pulse (unit peak at t = 0, t in samples) and its template."""

    def __init__(self, d):
        self.sr, self.sf = d["sigma_rise"], d["sigma_fall"]
        self.lo, self.hi = d["support"]
        self.taps = np.asarray(d["taps"], dtype=np.float64)
        self.peak_tap = d["peak_tap"]
        self.norm = float(np.sqrt(np.sum(self.taps**2)))
        self.frac = d["fraction_offset"]
        self.fwhm = d["fwhm"]

    def vs(self, t):
        s = np.where(t < 0.0, self.sr, self.sf)
        z = t / s
        v = np.exp(-0.5 * z * z)
        return v, -v * z / s


class Correlator:
    """Matched filter of whole frames, output indexed by peak position:
    y[p] = sum_j (x[p - peak_tap + j] - mean) taps[j] / |taps| (zero outside)."""

    def __init__(self, shape, n):
        self.t, self.pk = len(shape.taps), shape.peak_tap
        self.nfft = sfft.next_fast_len(n + self.t - 1, real=True)
        # Convolution with the reversed taps: c[m] = sum_i x[m - (t - 1) + i] taps[i],
        # so y[p] = c[p - peak_tap + t - 1], a contiguous slice.
        self.h = sfft.rfft(shape.taps[::-1] / shape.norm, self.nfft)
        self.n = n

    def run(self, xc):
        c = sfft.irfft(sfft.rfft(xc, self.nfft, axis=1) * self.h, self.nfft, axis=1)
        a = self.t - 1 - self.pk
        return c[:, a : a + self.n]


def window(x, first, length):
    """x[i, first[i] : first[i] + length] with indices past the edges clamped, and the mask of valid ones."""
    n = x.shape[1]
    k = first[:, None] + np.arange(length)
    ok = (k >= 0) & (k < n)
    return np.take_along_axis(x, np.clip(k, 0, n - 1), axis=1), k, ok


def parabolic(ym, y0, yp):
    den = ym - 2.0 * y0 + yp
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(den < 0.0, 0.5 * (ym - yp) / den, 0.0)
    return np.clip(d, -0.5, 0.5)


def fit_pulse(x, mean, shape, p0, iters=30, tol=1e-4):
    """Gauss-Newton ML fit of a * shape(k - d) to x - mean over
    [floor(p0 + lo), ceil(p0 + hi)] (amplitude solved in closed form, the
    delay stepped), all frames at once. Returns (d, a, rss, samples)."""
    first = np.floor(p0 + shape.lo).astype(np.int64)
    last = np.ceil(p0 + shape.hi).astype(np.int64) + 1
    length = int((last - first).max()) if len(p0) else 1
    xw, k, ok = window(x, first, length)
    ok &= k < last[:, None]
    y = np.where(ok, xw - mean[:, None], 0.0)
    d = p0.astype(np.float64).copy()
    kf = k.astype(np.float64)
    for _ in range(iters):
        s, g = shape.vs(kf - d[:, None])
        s *= ok
        g *= ok
        ss, sy, gg = (s * s).sum(1), (s * y).sum(1), (g * g).sum(1)
        sg, gy = (s * g).sum(1), (g * y).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = sy / ss
            step = -(gy - a * sg) / (a * (gg - sg * sg / ss))
        step = np.clip(np.nan_to_num(step), -1.0, 1.0)
        d += step
        if np.all(np.abs(step) < tol):
            break
    s, _ = shape.vs(kf - d[:, None])
    s *= ok
    ss, sy = (s * s).sum(1), (s * y).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = sy / ss
    rss = ((y - a[:, None] * s) ** 2).sum(1)
    return d, a, rss, ok.sum(1)


def crlb(shape, n, peak, amp, sigma):
    length = int(np.ceil(shape.hi - shape.lo)) + 2
    first = np.floor(peak + shape.lo)
    k = first[:, None] + np.arange(length)
    ok = (k >= 0) & (k <= np.minimum(np.ceil(peak + shape.hi), n - 1)[:, None])
    _, g = shape.vs(k - peak[:, None])
    e = ((g * ok) ** 2).sum(1)
    with np.errstate(divide="ignore"):
        return sigma / (np.abs(amp) * np.sqrt(e))


class Peer:
    def __init__(self, h):
        self.h = h
        self.n = h["samples"]
        self.dt = h["sample_interval_s"]
        self.stop = Shape(h["stop_shape"])
        self.corr = Correlator(self.stop, self.n)
        self.idx = np.arange(self.n)
        self.z_cell = stats.norm.isf(h["pfa_cell"])
        self.dc = self.stop.taps.sum() / self.stop.norm
        if h["mode"] == "full":
            self.start = Shape(h["start_shape"])
            t = len(self.stop.taps)
            # Pooled gate autocovariance (sum of products, pair counts), lags 0..t-1.
            self.acov = np.zeros(t)
            self.pairs = np.zeros(t)
            self.nfft_ac = sfft.next_fast_len(self.n + t, real=True)
            self.taps_acf = np.correlate(self.stop.taps, self.stop.taps, "full")[t - 1 :] / self.stop.norm**2
            self.held = None  # (level, mean) of the previous frame
            self.fa = np.zeros(3)  # observed, cells, expected
            ev = h["events"]
            self.flank = ev["flank"]
            self.fit_alpha = ev["fit_alpha"]
            self.ev_len = int(np.ceil(self.stop.hi) + self.flank - (np.floor(self.stop.lo) - self.flank)) + 1
            self.band = band_basis(self.ev_len, ev["max_frequency"])
            self.null_values = np.zeros(0)
            self.null_fresh = 0
            self.null_limit = None
            ln_nu = np.linspace(np.log(0.3), np.log(1e4), 4096)
            nu = np.exp(ln_nu)
            spread = (special.chdtri(nu, 0.25) - special.chdtri(nu, 0.75)) / special.chdtri(nu, 0.5)
            # Spread falls with nu: reversed for np.interp.
            self.spread_table = (spread[::-1], ln_nu[::-1])
        self.stats = {"jb_p_min": 1.0, "contaminated": 0, "events": 0, "components": 0, "fa_observed": 0}

    # --- start ---------------------------------------------------------------
    def start_stage(self, codes, offsets):
        h, sh, n = self.h, self.start, self.n
        x = codes * h["start_volts_per_code"] + h["start_offset_v"]
        peak = x.argmax(1)
        a = np.clip(np.floor(peak + 2.0 * sh.lo), 0, n).astype(np.int64)
        b = np.maximum(np.clip(np.ceil(peak + 2.0 * sh.hi) + 1, 0, n).astype(np.int64), a)
        # Sums off the pulse: the whole channel's less the pulse window's.
        wlen = int((b - a).max())
        xw, _, ok = window(x, a, wlen)
        ok &= (a[:, None] + np.arange(wlen)) < b[:, None]
        xw = np.where(ok, xw, 0.0)
        cnt = n - (b - a)
        mean = (x.sum(1) - xw.sum(1)) / cnt
        ss = (np.einsum("ij,ij->i", x, x) - np.einsum("ij,ij->i", xw, xw)) - cnt * mean * mean
        lsb = h["start_volts_per_code"]
        sigma = np.sqrt(ss / (cnt - 1) + lsb * lsb / 12.0)
        amp = x[np.arange(len(x)), peak] - mean
        found = amp >= np.maximum(h["start_min_amplitude_v"], 6.0 * sigma)
        # Matched filter around the peak: the outputs within half a FWHM of it.
        w_half = int(np.ceil(sh.fwhm * 0.5)) + 1
        t = len(sh.taps)
        first = peak - w_half - sh.peak_tap - 1
        xw, _, ok = window(x, first, 2 * w_half + 3 + t - 1)
        xw = np.where(ok, xw - mean[:, None], 0.0)
        y = np.lib.stride_tricks.sliding_window_view(xw, t, axis=1) @ (sh.taps / sh.norm)
        j = y[:, 1:-1].argmax(1) + 1
        r = np.arange(len(x))
        p0 = peak - w_half - 1 + j + parabolic(y[r, j - 1], y[r, j], y[r, j + 1])
        d, amp_fit, _, _ = fit_pulse(x, mean, sh, p0)
        # Shape mismatch: chi^2 of the least-squares amplitude at 17 positions around the fit.
        pos = d[:, None] + 0.25 * np.arange(-8, 9)
        length = int(np.ceil(sh.hi - sh.lo)) + 3
        fw = np.floor(d + sh.lo).astype(np.int64) - 2
        xs, k, ok = window(x, fw, length + 4)
        xs = np.where(ok, xs - mean[:, None], 0.0)
        tt = k[:, None, :] - pos[:, :, None]
        inside = ok[:, None, :] & (tt >= sh.lo) & (tt <= sh.hi)
        s, _ = sh.vs(tt)
        s = np.where(inside, s, 0.0)
        sss, sxs = (s * s).sum(2), (s * xs[:, None, :]).sum(2)
        xx = (np.where(inside, xs[:, None, :], 0.0) ** 2).sum(2)
        chi2 = np.min(np.maximum(xx - sxs * sxs / sss, 0.0), axis=1) / sigma**2
        self.stats["start_chi2_mean"] = float(chi2.mean())
        t_ref = np.where(found, offsets + (d + sh.frac) * self.dt, h["reference_offset_s"])
        t_ref_sigma = np.where(found, crlb(sh, n, d, amp_fit, sigma) * self.dt, 0.0)
        return t_ref, t_ref_sigma

    # --- noise ---------------------------------------------------------------
    def gates(self, t_ref, offsets):
        h, sh, n = self.h, self.stop, self.n
        idx = lambda t: (t - offsets) / self.dt
        c = h["c_m_per_s"]
        peak_at = lambda tof: idx(t_ref + h["delay_s"] + tof) - sh.frac
        p_min = peak_at(2.0 * h["range_m"][0] / c) - sh.fwhm
        p_max = peak_at(2.0 * h["range_m"][1] / c) + sh.fwhm
        clamp = lambda v: np.clip(v, 0, n).astype(np.int64)
        r0, r1 = clamp(np.ceil(p_min - 1e-6)), clamp(np.floor(p_max + 1e-6) + 1)
        guard = h["guard_s"] / self.dt
        pre_end = clamp(np.floor(np.minimum(idx(t_ref) - guard, p_min + sh.lo - guard) + 1e-6))
        beyond = clamp(np.ceil(p_max + sh.hi + guard - 1e-6))
        return r0, r1, pre_end, beyond

    def robust_sigma(self, codes, gate, n_gate):
        """tofwave's robust sigma for samples on a grid: probit fit of the
        gate codes' cumulative histogram at the cell boundaries inside the
        10-90 % points (at most 32 of them), per frame, all at once."""
        vpc = self.h["stop_volts_per_code"]
        big = np.iinfo(np.int32).max
        lo = np.where(gate, codes, big).min(1)
        hi = np.where(gate, codes, -big).max(1)
        levels = int((hi - lo).max()) + 1
        rows = np.arange(len(codes))[:, None]
        flat = ((codes - lo[:, None]) + rows * levels)[gate]
        counts = np.bincount(flat, minlength=len(codes) * levels).reshape(len(codes), levels)
        f = np.cumsum(counts[:, :-1], axis=1) / n_gate[:, None]
        inside = (f >= 0.1) & (f <= 0.9)
        m = inside.sum(1)
        stride = np.maximum(-(-m // 32), 1)
        seen = np.cumsum(inside, axis=1)
        use = inside & ((seen - 1) % stride[:, None] == 0)
        fc = np.where(use, f, 0.5)
        z = np.where(use, special.ndtri(fc), 0.0)
        w = np.where(use, np.exp(-z * z) / (2 * np.pi) / (fc * (1 - fc)), 0.0)
        xb = np.arange(levels - 1) + 0.5
        sw, swx, swy = w.sum(1), (w * xb).sum(1), (w * z).sum(1)
        swxx, swxy = (w * xb * xb).sum(1), (w * xb * z).sum(1)
        slope = (sw * swxy - swx * swy) / (sw * swxx - swx * swx)
        sig = vpc / slope
        return np.sqrt(sig * sig + vpc * vpc / 12.0)

    def noise_stage(self, codes, x, gates):
        h = self.h
        r0, r1, pre_end, beyond = gates
        gate = (self.idx < pre_end[:, None]) | (self.idx >= beyond[:, None])
        ng = gate.sum(1)
        # Only the columns some frame's gate covers (the range gate between them is skipped).
        cols = np.r_[0 : int(pre_end.max()), int(beyond.min()) : self.n]
        xg, gg = x[:, cols], gate[:, cols]
        mean = np.where(gg, xg, 0.0).sum(1) / ng
        devg = np.where(gg, xg - mean[:, None], 0.0)
        d2 = devg * devg
        m2, m3, m4 = d2.sum(1), (d2 * devg).sum(1), (d2 * d2).sum(1)
        dev = np.zeros_like(x)
        dev[:, cols] = devg
        sigma = np.sqrt(m2 / (ng - 1))
        skew = (m3 / ng) / (m2 / ng) ** 1.5
        kurt = (m4 / ng) / (m2 / ng) ** 2 - 3.0
        jb = ng / 6.0 * (skew * skew + kurt * kurt / 4.0)
        p = np.exp(-0.5 * jb)
        robust = self.robust_sigma(codes[:, cols], gg, ng)
        c4 = 1.0 - 1.0 / (4.0 * ng) - 7.0 / (32.0 * ng * ng)
        diff = sigma / c4 - robust * ng / (ng - 0.8)
        z = stats.norm.isf(0.5 * h["normality_alpha"])
        contaminated = np.abs(diff) > z * 1.0 * robust / np.sqrt(ng)
        self.stats["jb_p_min"] = min(self.stats["jb_p_min"], float(p.min()))
        self.stats["contaminated"] += int(contaminated.sum())
        lsb = h["stop_volts_per_code"]
        sigma = np.maximum(sigma, lsb / np.sqrt(12.0))
        return gate, ng, mean, sigma, dev

    # --- detect --------------------------------------------------------------
    def colour(self, dev, pre_len, beyond_len):
        """Pooled gate autocovariance (FFT of the centred gate samples, zero
        elsewhere: the gap between the gates is longer than the lags), the
        output's variance gain and lag-1 correlation after each frame."""
        t = len(self.acov)
        spec = sfft.rfft(dev, self.nfft_ac, axis=1)
        ac = sfft.irfft(spec * np.conj(spec), self.nfft_ac, axis=1)[:, :t]
        lags = np.arange(t)
        pairs = np.maximum(pre_len[:, None] - lags, 0) + np.maximum(beyond_len[:, None] - lags, 0)
        acov = self.acov + np.cumsum(ac, axis=0)
        cnt = self.pairs + np.cumsum(pairs, axis=0)
        self.acov, self.pairs = acov[-1], cnt[-1]
        rho = (acov / cnt) / (acov[:, :1] / cnt[:, :1])
        # White unless the excess of sum rho^2 is 4 sd clear of its estimation noise.
        v1 = (1.0 / cnt[:, 1:]).sum(1)
        v2 = (1.0 / cnt[:, 1:] ** 2).sum(1)
        raw = (rho * rho).sum(1) + (rho[:, 1:] ** 2).sum(1)
        coloured = raw - 1.0 - 2.0 * v1 > 4.0 * 2.0 * np.sqrt(2.0 * v2)
        g = np.where(coloured, 1.0 + 2.0 * (rho[:, 1:] * self.taps_acf[1:]).sum(1), 1.0)
        self.stats["rho1_last"] = float(rho[-1, 1])
        return np.sqrt(np.maximum(g, 1e-6))

    def threshold(self, ng, sigma, out_gain):
        nu = ng - 1.0
        t = -special.stdtrit(nu, self.h["pfa_cell"])
        kappa = np.sqrt(1.0 + self.dc * self.dc / ng)
        return t * kappa * sigma * out_gain, t, kappa, nu

    def false_alarms(self, y, mean, thr, gate, ng):
        """Up-crossings of the previous frame's level in the noise-gate
        outputs (template wholly inside a gate), cumulative, Clopper-Pearson."""
        t, pk = len(self.stop.taps), self.stop.peak_tap
        pre_end, beyond = gate
        # Output positions whose template lies wholly inside a gate.
        i = self.idx
        pos = ((i >= pk) & (i < (pre_end + pk + 1 - t)[:, None])) | ((i >= (beyond + pk)[:, None]) & (i < self.n + pk + 1 - t))
        prev_thr = np.concatenate([[np.inf if self.held is None else self.held[0]], thr[:-1]])
        prev_mean = np.concatenate([[mean[0] if self.held is None else self.held[1]], mean[:-1]])
        level = prev_thr - self.dc * (mean - prev_mean)
        above = (y > level[:, None]) & pos
        up = above & ~np.concatenate([np.zeros((len(y), 1), bool), above[:, :-1]], axis=1)
        observed = up.sum(1)
        cells = np.where(np.isfinite(prev_thr), pos.sum(1), 0)
        obs_c = self.fa[0] + np.cumsum(observed)
        cells_c = self.fa[1] + np.cumsum(cells)
        self.fa[0], self.fa[1] = obs_c[-1], cells_c[-1]
        self.held = (thr[-1], mean[-1])
        trials = np.maximum(np.round(cells_c), 1)
        succ = np.minimum(obs_c, trials)
        with np.errstate(invalid="ignore"):
            lo95 = np.where(succ > 0, special.betaincinv(succ, trials - succ + 1, 0.025), 0.0)
            hi95 = np.where(succ < trials, special.betaincinv(succ + 1, trials - succ, 0.975), 1.0)
            lo998 = np.where(succ > 0, special.betaincinv(succ, trials - succ + 1, 0.001), 0.0)
        excess = lo998 > self.h["pfa_cell"]
        self.stats["fa_observed"] = int(obs_c[-1])
        self.stats["fa_excess_frames"] = self.stats.get("fa_excess_frames", 0) + int(excess.sum())
        self.stats["fa_ci95_last"] = [float(lo95[-1]), float(hi95[-1])]

    # --- resolve ---------------------------------------------------------------
    def resolve(self, x, mean, sigma, y, thr, r0, r1, max_pulses=32):
        """Successive cancellation over all frames: returns per frame a list of (peak, amplitude, misfit)."""
        sh, n = self.stop, self.n
        t = len(sh.taps)
        inrange = (self.idx >= r0[:, None]) & (self.idx < r1[:, None])
        yr = np.where(inrange, y, -np.inf)
        out = [[] for _ in range(len(x))]
        rows = np.arange(len(x))
        resid = x - mean[:, None]
        zero = np.zeros(len(x))
        for _ in range(max_pulses):
            p = yr.argmax(1)
            v = yr[np.arange(len(rows)), p]
            go = v > thr[rows]
            if not go.any():
                break
            rows, p, yr, resid = rows[go], p[go], yr[go], resid[go]
            rr = np.arange(len(rows))
            pm, pp = np.maximum(p - 1, 0), np.minimum(p + 1, n - 1)
            p0 = p + parabolic(yr[rr, pm], yr[rr, p], yr[rr, pp])
            d, a, rss, m = fit_pulse(resid, zero[: len(rows)], sh, p0)
            bad = ~(a > 0)
            a = np.where(bad, yr[rr, p] / sh.norm, a)
            d = np.where(bad, p0, d)
            misfit = np.sqrt(rss / np.maximum(m, 1)) / sigma[rows]
            for i, r in enumerate(rows):
                out[r].append((d[i], a[i], misfit[i]))
            # Subtract the pulse and update the filter output where it reaches.
            first = np.floor(d + sh.lo).astype(np.int64)
            length = int(np.ceil(sh.hi - sh.lo)) + 2
            k = first[:, None] + np.arange(length)
            ok = (k >= 0) & (k < n) & (k <= np.ceil(d + sh.hi)[:, None])
            s, _ = sh.vs(k - d[:, None])
            pulse = np.where(ok, a[:, None] * s, 0.0)
            kc = np.clip(k, 0, n - 1)
            resid[rr[:, None], kc] -= pulse
            padded = np.pad(pulse, ((0, 0), (t - 1, t - 1)))
            contrib = np.lib.stride_tricks.sliding_window_view(padded, t, axis=1) @ (sh.taps / sh.norm)
            q = first[:, None] + sh.peak_tap - (t - 1) + np.arange(length + t - 1)
            qok = (q >= 0) & (q < n)
            qc = np.clip(q, 0, n - 1)
            yr[rr[:, None], qc] -= np.where(qok, contrib, 0.0)
        return out

    # --- events --------------------------------------------------------------
    def learn_null(self, x, mean, sigma, pre_end, beyond):
        L, n = self.ev_len, self.n
        npre = pre_end // L
        nbey = (n - beyond) // L
        most_pre, most_bey = int(npre.max()), int(nbey.max())
        parts = []
        for starts, count, most in ((np.zeros_like(pre_end), npre, most_pre), (beyond, nbey, most_bey)):
            if most == 0:
                continue
            st = starts[:, None] + L * np.arange(most)
            k = st[:, :, None] + np.arange(L)
            xw = np.take_along_axis(x, np.clip(k, 0, n - 1).reshape(len(x), -1), 1).reshape(len(x), most, L)
            e = ((xw - mean[:, None, None]) @ self.band) ** 2
            parts.append((e.sum(2) / sigma[:, None] ** 2, np.arange(most) < count[:, None]))
        energies = np.concatenate([e for e, _ in parts], axis=1)
        ok = np.concatenate([o for _, o in parts], axis=1)
        # Frame after frame, pre-gate windows before beyond-gate ones: the order tofwave sees them in.
        allv = np.concatenate([self.null_values, energies[ok]])
        ends = len(self.null_values) + np.cumsum(ok.sum(1))
        counts = ok.sum(1)
        limits = np.empty(len(x))
        for f in range(len(x)):
            self.null_fresh += int(counts[f])
            have = min(int(ends[f]), 2048)
            if have >= 64 and (self.null_fresh >= 64 or self.null_limit is None):
                self.null_fresh = 0
                srt = np.sort(allv[ends[f] - have : ends[f]])
                at = lambda q: srt[int(round((have - 1) * q))]
                q1, med, q3 = at(0.25), at(0.5), at(0.75)
                nu = self.dof_from_spread((q3 - q1) / med)
                self.null_limit = med / special.chdtri(nu, 0.5) * special.chdtri(nu, self.fit_alpha)
            if self.null_limit is None:
                # Too few windows yet: white noise's null (the band's column count).
                self.null_limit = special.chdtri(self.band.shape[1], self.fit_alpha)
            limits[f] = self.null_limit
        self.null_values = allv[-2048:]
        return limits

    def dof_from_spread(self, spread):
        """Degrees of freedom of the chi^2 whose interquartile range over its
        median is `spread`: interpolated in a table made once (ln nu over
        [0.3, 1e4]) instead of tofwave's per-call bisection."""
        return float(np.exp(np.interp(spread, self.spread_table[0], self.spread_table[1])))

    def judge(self, x, mean, sigma, u, comps, limits):
        """Step 1 for every return (batched): the energy the band explains
        beyond the return's pulse and slope, against the learned limit.
        Step 2 (rare) per return: z of the pulse projected off the band."""
        sh, L, n, Q = self.stop, self.ev_len, self.n, self.band
        fr = np.array([f for f, c in enumerate(comps) for _ in c], dtype=np.int64)
        if len(fr) == 0:
            return comps
        c = np.array([p for cs in comps for (p, _, _) in cs])
        first = np.clip(np.floor(c + sh.lo).astype(np.int64) - self.flank, 0, n - L)
        k = first[:, None] + np.arange(L)
        xw = np.take_along_axis(x[fr], k, 1) - mean[fr, None]
        s, g = sh.vs(k - c[:, None])
        P = np.stack([s, g], axis=2)
        ptp = P.transpose(0, 2, 1) @ P
        ptx = np.einsum("fli,fl->fi", P, xw)
        alone = np.einsum("fi,fi->f", ptx, np.linalg.solve(ptp, ptx[..., None])[..., 0])
        qx = xw @ Q
        xp = xw - qx @ Q.T
        Pp = P - Q @ (Q.T @ P)
        pptp = Pp.transpose(0, 2, 1) @ Pp
        pptx = np.einsum("fli,fl->fi", Pp, xp)
        both = (qx * qx).sum(1) + np.einsum("fi,fi->f", pptx, np.linalg.solve(pptp, pptx[..., None])[..., 0])
        explained = np.maximum(both - alone, 0.0) / sigma[fr] ** 2
        event = explained > limits[fr]
        keep = np.ones(len(fr), bool)
        for i in np.nonzero(event)[0]:
            q = s[i] - Q @ (Q.T @ s[i])
            z = q @ xw[i] / (sigma[fr[i]] * np.sqrt(q @ q))
            keep[i] = z > u[fr[i]]
        self.stats["events"] += int((~keep).sum())
        out, i = [], 0
        for cs in comps:
            out.append([cp for j, cp in enumerate(cs) if keep[i + j]])
            i += len(cs)
        return out

    # --- the frames ----------------------------------------------------------
    def full(self, start_codes, stop_codes, offsets):
        h, sh, n, dt = self.h, self.stop, self.n, self.dt
        t_ref, t_ref_sigma = self.start_stage(start_codes, offsets)
        x = stop_codes * h["stop_volts_per_code"] + h["stop_offset_v"]
        gates = self.gates(t_ref, offsets)
        r0, r1, pre_end, beyond = gates
        gate, ng, mean, sigma, dev = self.noise_stage(stop_codes, x, gates)
        out_gain = self.colour(dev, pre_end, self.n - beyond)
        thr, t, kappa, nu = self.threshold(ng, sigma, out_gain)
        y = self.corr.run(x - mean[:, None])
        self.false_alarms(y, mean, thr, (pre_end, beyond), ng)
        comps = self.resolve(x, mean, sigma, y, thr, r0, r1)
        limits = self.learn_null(x, mean, sigma, pre_end, beyond)
        comps = self.judge(x, mean, sigma, thr / (sigma * out_gain), comps, limits)
        # Timing, every return of the batch at once.
        fr = np.array([f for f, cs in enumerate(comps) for _ in cs], dtype=np.int64)
        peak = np.array([p for cs in comps for (p, _, _) in cs])
        amp = np.array([a for cs in comps for (_, a, _) in cs])
        self.stats["components"] += len(fr)
        c = h["c_m_per_s"]
        sig = crlb(sh, n, peak, amp, sigma[fr])
        t_stop = offsets[fr] + (peak + sh.frac) * dt
        tof = t_stop - t_ref[fr] - h["delay_s"]
        sigma_t = np.sqrt((sig * dt) ** 2 + t_ref_sigma[fr] ** 2 + h["delay_sigma_s"] ** 2)
        d = amp * sh.norm / (sigma[fr] * out_gain[fr])
        tf = t[fr]
        pd = special.ndtr(-(tf - d / kappa[fr]) / np.sqrt(1.0 + tf * tf / (2.0 * nu[fr])))
        snr_db = 20 * np.log10(np.abs(amp) / sigma[fr])
        res = [[] for _ in comps]
        for j in np.lexsort((tof, fr)):
            res[fr[j]].append({"t_stop_s": t_stop[j], "range_m": 0.5 * c * tof[j], "range_sigma_m": 0.5 * c * sigma_t[j], "snr_db": snr_db[j], "pd": pd[j]})
        return res

    def minimal(self, stop_codes, offsets):
        h, sh, n, dt = self.h, self.stop, self.n, self.dt
        x = stop_codes * h["stop_volts_per_code"] + h["stop_offset_v"]
        t_ref = np.full(len(x), h["reference_offset_s"])
        r0, r1, pre_end, beyond = self.gates(t_ref, offsets)
        gate = (self.idx < pre_end[:, None]) | (self.idx >= beyond[:, None])
        ng = gate.sum(1)
        mean = np.where(gate, x, 0.0).sum(1) / ng
        sigma = np.sqrt(np.where(gate, (x - mean[:, None]) ** 2, 0.0).sum(1) / (ng - 1))
        y = self.corr.run(x - mean[:, None])
        yr = np.where((self.idx >= r0[:, None]) & (self.idx < r1[:, None]), y, -np.inf)
        p = yr.argmax(1)
        rr = np.arange(len(x))
        hit = yr[rr, p] > self.z_cell * sigma
        p0 = p + parabolic(y[rr, np.maximum(p - 1, 0)], y[rr, p], y[rr, np.minimum(p + 1, n - 1)])
        d, a, _, _ = fit_pulse(x, mean, sh, p0)
        t_stop = offsets + (d + sh.frac) * dt
        c = h["c_m_per_s"]
        return [[{"t_stop_s": t_stop[f], "range_m": 0.5 * c * (t_stop[f] - t_ref[f] - h["delay_s"])}] if hit[f] and a[f] > 0 else [] for f in range(len(x))]


def band_basis(length, f_max):
    """Orthonormal basis of cos/sin(2 pi f (i - mid)), f = 0, 1/(2 length), ... <= f_max."""
    df = 0.5 / length
    mid = 0.5 * (length - 1)
    i = np.arange(length) - mid
    cols = []
    k = 0
    while k * df <= f_max * (1 + 1e-12):
        w = 2 * np.pi * k * df
        cols.append(np.cos(w * i))
        if k > 0:
            cols.append(np.sin(w * i))
        k += 1
    q, _ = np.linalg.qr(np.stack(cols, axis=1))
    return q


def main(header_path, out_path):
    with open(header_path) as f:
        h = json.load(f)
    frames, n = h["frames"], h["samples"]
    stop = np.fromfile(h["stop_file"], dtype="<i2").reshape(frames, n)
    start = np.fromfile(h["start_file"], dtype="<i2").reshape(frames, n) if h["mode"] == "full" else None
    offsets = np.asarray(h["first_sample_offset_s"], dtype=np.float64)
    # Best of `repeats` passes (fresh state each), as tofwave's side is timed;
    # the first `warmup_frames` (whole batches) of each pass off the clock,
    # as on tofwave's side (start-up, not per-frame work).
    warmup = min(int(h.get("warmup_frames", 0)) // BATCH * BATCH, max(frames - BATCH, 0))
    best = np.inf
    for _ in range(max(int(h.get("repeats", 1)), 1)):
        peer = Peer(h)
        out = []
        t0 = time.perf_counter()
        for b in range(0, frames, BATCH):
            if b == warmup:
                t0 = time.perf_counter()
            e = min(b + BATCH, frames)
            # Codes as int32 (the histogram) and float64 (the arithmetic).
            sc = stop[b:e].astype(np.int32)
            if h["mode"] == "full":
                out.extend(peer.full(start[b:e].astype(np.int32), sc, offsets[b:e]))
            else:
                out.extend(peer.minimal(sc, offsets[b:e]))
        best = min(best, time.perf_counter() - t0)
    elapsed = best
    clean = lambda v: {k: float(x) for k, x in v.items()}
    with open(out_path, "w") as f:
        json.dump(
            {
                "returns": [[clean(r) for r in rets] for rets in out],
                "ns_per_frame": elapsed * 1e9 / max(frames - warmup, 1),
                "stats": peer.stats,
                "versions": "python %s, numpy %s, scipy %s; %d frames a batch"
                % (sys.version.split()[0], np.__version__, scipy.__version__, BATCH),
            },
            f,
        )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
