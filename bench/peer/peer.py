#!/usr/bin/env python3
"""The numpy/scipy peer of tofwave's pipeline, as a researcher would write it.

Used only by `tofwave bench`, which writes the frames (raw little-endian i16
codes of the stop channel, one frame after another) and a JSON header, runs
this script on them in the same invocation, and compares the ranges and the
time per frame.

Per frame: codes to volts; noise-gate mean and standard deviation; matched
filter (scipy.signal.correlate with the same template taps); threshold at the
same per-cell false-alarm probability through the Gaussian inverse tail
Q^-1 (scipy.stats.norm.isf); the largest peak above it in the search window;
parabolic interpolation of the peak; then a maximum-likelihood fit of the
delay (amplitude solved in closed form, delay by scipy.optimize.minimize_scalar)
with the same pulse shape. The timing point is the same fraction crossing of
the fitted shape that tofwave reports as t_stop_s.

usage: peer.py HEADER.json OUT.json
"""

import json
import sys
import time

import numpy as np
import scipy
from scipy import optimize, signal, stats


def main(header_path, out_path):
    with open(header_path) as f:
        h = json.load(f)
    n_frames, n = h["frames"], h["samples"]
    raw = np.fromfile(h["samples_file"], dtype="<i2").reshape(n_frames, n)
    dt = h["sample_interval_s"]
    vpc, off = h["volts_per_code"], h["offset_v"]
    taps = np.asarray(h["template"], dtype=np.float64)
    peak_index = h["template_peak_index"]
    norm = np.sqrt(np.sum(taps * taps))
    g0, g1 = h["noise_gate"]
    s0, s1 = h["search"]
    # Same per-cell false-alarm probability as tofwave's threshold.
    z_threshold = stats.norm.isf(h["pfa_cell"])
    # Pulse shape on a fine grid (unit peak at 0), for the ML fit.
    shape_t = np.asarray(h["shape_t"], dtype=np.float64)
    shape_v = np.asarray(h["shape_v"], dtype=np.float64)
    lo, hi = shape_t[0], shape_t[-1]
    fraction_offset = h["fraction_offset"]
    offsets = h["first_sample_offset_s"]

    def shape(t):
        return np.interp(t, shape_t, shape_v, left=0.0, right=0.0)

    out = []
    t0 = time.perf_counter()
    for k in range(n_frames):
        x = raw[k].astype(np.float64) * vpc + off
        gate = x[g0:g1]
        mu = gate.mean()
        sigma = gate.std(ddof=1)
        xc = x - mu
        # y[i] = sum_j xc[i + j] taps[j]: a pulse peaking at sample p gives its maximum at i = p - peak_index.
        y = signal.correlate(xc, taps, mode="valid") / (sigma * norm)
        i0, i1 = max(s0 - peak_index, 1), min(s1 - peak_index, len(y) - 1)
        w = y[i0:i1]
        i = int(np.argmax(w)) + i0
        if y[i] < z_threshold:
            out.append(None)
            continue
        den = y[i - 1] - 2.0 * y[i] + y[i + 1]
        delta = 0.5 * (y[i - 1] - y[i + 1]) / den if den < 0 else 0.0
        p0 = i + peak_index + delta
        k0 = max(int(np.floor(p0 + lo)), 0)
        k1 = min(int(np.ceil(p0 + hi)) + 1, n)
        kk = np.arange(k0, k1, dtype=np.float64)
        seg = xc[k0:k1]

        def cost(tau):
            s = shape(kk - tau)
            ss = np.dot(s, s)
            if ss <= 0:
                return np.dot(seg, seg)
            a = np.dot(seg, s) / ss
            r = seg - a * s
            return np.dot(r, r)

        fit = optimize.minimize_scalar(cost, bounds=(p0 - 1.5, p0 + 1.5), method="bounded", options={"xatol": 1e-4})
        tau = fit.x
        out.append(offsets[k] + (tau + fraction_offset) * dt)
    elapsed = time.perf_counter() - t0
    with open(out_path, "w") as f:
        json.dump(
            {
                "t_stop_s": out,
                "ns_per_frame": elapsed * 1e9 / max(n_frames, 1),
                "versions": "python %s, numpy %s, scipy %s"
                % (sys.version.split()[0], np.__version__, scipy.__version__),
            },
            f,
        )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
