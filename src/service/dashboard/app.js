// tofwave dashboard: vanilla JS, <canvas> drawing, fed by server-sent events
// from /events (the same report stream gRPC subscribers get). No framework,
// no network beyond this server.
'use strict';

const WINDOW_S = 60;            // strip chart span, seconds
const MAX_RETURNS = 20000;      // returns kept per sensor for the strip chart
const SNR_MIN_DB = 0, SNR_MAX_DB = 40;
const IDLE_S = 5;               // no frame for this long: idle
const INFO_FLAGS = ['no_start_channel']; // report flags that describe the set-up, not a fault

const params = new URLSearchParams(location.search);
const token = params.get('token');
const onlySensors = params.getAll('sensor');
const root = document.getElementById('dash');
const $ = (id) => document.getElementById(id);

const state = {
  sensors: new Map(),   // id -> sensor state
  selected: params.get('select'),
  clockOffsetMs: null,  // server clock - browser clock (largest seen: transit only shortens it)
  skipped: 0,           // reports this page skipped (it fell behind)
  maxDelayMs: 0,        // largest report-to-screen delay
  lastDelayMs: null,
  reports: 0,
  liveFromMs: null,     // server time of connection: older reports are history, not live
  dirty: true,
};

function sensor(id) {
  let s = state.sensors.get(id);
  if (!s) {
    s = { id, returns: [], report: null, waveform: null, status: null, prev: null,
          pending: [], health: 'idle', why: '' };
    state.sensors.set(id, s);
    if (!state.selected) state.selected = id;
  }
  return s;
}

function serverNow() { return Date.now() + (state.clockOffsetMs || 0); }

// ---------------------------------------------------------------- events
function query(extra) {
  const q = new URLSearchParams();
  for (const s of onlySensors) q.append('sensor', s);
  if (token) q.set('token', token);
  const str = q.toString();
  return str ? '?' + str : '';
}

function connect() {
  const es = new EventSource('events' + query());
  es.onopen = () => setConn('ok', 'live');
  es.onerror = () => {
    if (es.readyState === EventSource.CLOSED) {
      // EventSource gives up on HTTP errors: ask why (401 without the token).
      fetch('api/sensors' + query()).then(async (r) => {
        if (!r.ok) showBanner(`${r.status}: ${(await r.text()).trim()}`);
      }).catch(() => {});
      setConn('bad', 'disconnected');
      setTimeout(connect, 3000);
    } else {
      setConn('warn', 'reconnecting…');
    }
  };
  es.addEventListener('hello', (e) => {
    const h = JSON.parse(e.data);
    $('server-info').textContent = `server ${h.version} · waveforms ≤ ${h.snapshot_max_points} points`;
    root.dataset.connected = '1';
    showBanner('');
    // A (re)connection resends the retained reports: start the chart afresh.
    for (const x of state.sensors.values()) x.returns.length = 0;
    state.liveFromMs = null;
  });
  es.addEventListener('report', (e) => {
    const { published_unix_ms: t, report } = JSON.parse(e.data);
    const s = sensor(report.sensor);
    s.report = report;
    for (const r of report.returns) {
      s.returns.push({ t, r: r.range_m, sig: r.range_sigma_m, snr: r.snr_db });
    }
    if (s.returns.length > MAX_RETURNS) s.returns.splice(0, s.returns.length - MAX_RETURNS);
    if (state.liveFromMs !== null && t >= state.liveFromMs) s.pending.push(t);
    state.reports++;
    state.dirty = true;
  });
  es.addEventListener('waveform', (e) => {
    const w = JSON.parse(e.data);
    sensor(w.sensor).waveform = w;
    state.dirty = true;
  });
  es.addEventListener('sensors', (e) => {
    const msg = JSON.parse(e.data);
    const off = msg.server_unix_ms - Date.now();
    if (state.clockOffsetMs === null || off > state.clockOffsetMs) state.clockOffsetMs = off;
    if (state.liveFromMs === null) state.liveFromMs = msg.server_unix_ms;
    for (const st of msg.sensors) {
      const s = sensor(st.sensor);
      s.prev = s.status;
      s.status = st;
    }
    state.dirty = true;
  });
  es.addEventListener('lagged', (e) => {
    state.skipped = JSON.parse(e.data).skipped_total;
    state.dirty = true;
  });
  es.addEventListener('closed', () => { setConn('idle', 'server shut down'); es.close(); });
}

function setConn(cls, text) {
  $('conn-dot').className = 'dot ' + cls;
  $('conn-text').textContent = text;
  if (cls !== 'ok') root.dataset.connected = '0';
}

function showBanner(text) {
  const b = $('banner');
  b.textContent = text;
  b.style.display = text ? 'block' : 'none';
}

// ---------------------------------------------------------------- health
function health(s) {
  const st = s.status, why = [];
  if (!st || st.idle_s === null || st.idle_s > IDLE_S) return ['idle', st ? `no frame for ${fmt(st.idle_s ?? 0, 0)} s` : 'no status yet'];
  if (s.prev && st.frames_rejected > s.prev.frames_rejected) why.push(`${st.frames_rejected - s.prev.frames_rejected} frames rejected`);
  if (s.prev && st.sequence_gaps > s.prev.sequence_gaps) why.push(`${st.sequence_gaps - s.prev.sequence_gaps} frames missing`);
  const r = s.report;
  if (r && r.false_alarm.excess) why.push('false alarms above design');
  if (r && !r.noise.gaussian) why.push('noise not Gaussian');
  const flags = r ? r.flags.filter((f) => !INFO_FLAGS.includes(f)) : [];
  if (flags.length) why.push('flags: ' + flags.join(', '));
  const info = r ? r.flags.filter((f) => INFO_FLAGS.includes(f)) : [];
  return why.length ? ['warn', why.join('; ')] : ['ok', 'frames arriving, none rejected' + (info.length ? ` (${info.join(', ')})` : '')];
}

// ---------------------------------------------------------------- text
function fmt(x, d = 3) {
  if (x === null || x === undefined || Number.isNaN(x)) return '–';
  if (!Number.isFinite(x)) return x > 0 ? '∞' : '−∞';
  const a = Math.abs(x);
  if (a !== 0 && (a < 1e-3 || a >= 1e6)) return x.toExponential(Math.max(1, d - 1));
  return x.toFixed(d);
}

function kv(el, pairs) {
  el.innerHTML = '';
  for (const [k, v] of pairs) {
    const a = document.createElement('span'); a.textContent = k;
    const b = document.createElement('span'); b.textContent = v;
    el.append(a, b);
  }
}

function renderText() {
  const rows = $('sensor-rows');
  const ids = [...state.sensors.keys()].sort();
  if (ids.length) rows.innerHTML = '';
  for (const id of ids) {
    const s = state.sensors.get(id), st = s.status || {};
    [s.health, s.why] = health(s);
    const tr = document.createElement('tr');
    if (id === state.selected) tr.className = 'sel';
    tr.onclick = () => { state.selected = id; state.dirty = true; };
    const cells = [id, '', fmt(st.frames_per_s ?? 0, 0), st.reports ?? '–', st.returns ?? '–', st.frames_rejected ?? '–'];
    cells.forEach((c, i) => {
      const td = document.createElement('td');
      if (i === 1) {
        const d = document.createElement('span'); d.className = 'dot ' + s.health; d.title = s.why;
        td.append(d, ' ' + s.health);
      } else td.textContent = c;
      tr.append(td);
    });
    rows.append(tr);
  }
  const s = state.sensors.get(state.selected);
  if (!s) return;
  root.dataset.sensor = s.id;
  root.dataset.health = s.health;
  $('title').firstChild.textContent = s.id;
  $('title-health').textContent = `${s.health}: ${s.why}`;
  $('health-why').textContent = '';
  const r = s.report, st = s.status || {};
  if (r) {
    const n = r.noise;
    kv($('card-noise'), [
      ['μ', fmt(n.mean_v * 1e3) + ' mV'], ['σ', fmt(n.sigma_v * 1e3) + ' mV'],
      ['normality', (n.gaussian ? 'Gaussian' : 'not Gaussian') + ` (JB p ${fmt(n.normality_p_value, 2)})`],
      ['skew / kurt', `${fmt(n.skewness, 2)} / ${fmt(n.excess_kurtosis, 2)}`],
      ['gate', `${n.samples} samples` + (n.contaminated ? ', cleaned' : '')],
    ]);
    const fa = r.false_alarm, d = r.detector;
    kv($('card-fa'), [
      ['observed', `${fa.observed} in ${fmt(fa.cells, 0)} cells`],
      ['rate', fmt(fa.rate)], ['95 % CI', `${fmt(fa.ci95[0])} … ${fmt(fa.ci95[1])}`],
      ['design', `${fmt(d.pfa_cell)} ` + (fa.excess ? '(exceeded)' : '(held)')],
    ]);
    drawFaCi(fa, d);
    kv($('card-det'), [
      ['kind', d.kind], ['pfa / report', fmt(d.pfa_design)], ['threshold', fmt(d.threshold * 1e3) + ' mV'],
      ['stages', r.stages.join(' → ')], ['frames / report', String(r.frames_averaged)],
    ]);
  }
  kv($('card-rate'), [
    ['frames/s', fmt(st.frames_per_s ?? 0, 1)],
    ['latency', fmt(st.latency_ms ?? null, 2) + ' ms queue → report'],
    ['queue', `${st.queue_frames ?? '–'} frames`],
    ['to screen', state.lastDelayMs === null ? '–' : `${fmt(state.lastDelayMs, 0)} ms (max ${fmt(state.maxDelayMs, 0)})`],
    ['skipped', `${state.skipped} reports (page fell behind)`],
  ]);
}

// ---------------------------------------------------------------- canvas
function setup(canvas) {
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth, h = Number(canvas.getAttribute('height'));
  if (canvas.width !== Math.round(w * dpr)) { canvas.width = Math.round(w * dpr); canvas.style.height = h + 'px'; }
  canvas.height = Math.round(h * dpr);
  const g = canvas.getContext('2d');
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  g.font = '11px system-ui, sans-serif';
  return [g, w, h];
}

// viridis, 5 stops
const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
function snrColour(db) {
  let u = (db - SNR_MIN_DB) / (SNR_MAX_DB - SNR_MIN_DB);
  u = Math.min(1, Math.max(0, Number.isFinite(u) ? u : 0)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(u)), f = u - i;
  const c = VIRIDIS[i].map((v, k) => Math.round(v + f * (VIRIDIS[i + 1][k] - v)));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

function niceTicks(lo, hi, n) {
  const span = hi - lo || 1, step0 = span / n, mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0) || step0;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * span; v += step) out.push(v);
  return out;
}

function axes(g, box, xlo, xhi, ylo, yhi, xlabel, ylabel) {
  const { x, y, w, h } = box;
  g.strokeStyle = '#2a333c'; g.fillStyle = '#8a96a3'; g.lineWidth = 1;
  for (const v of niceTicks(ylo, yhi, 5)) {
    const py = y + h - (v - ylo) / (yhi - ylo) * h;
    g.beginPath(); g.moveTo(x, py); g.lineTo(x + w, py); g.stroke();
    g.textAlign = 'right'; g.fillText(fmtTick(v), x - 4, py + 4);
  }
  for (const v of niceTicks(xlo, xhi, 8)) {
    const px = x + (v - xlo) / (xhi - xlo) * w;
    g.beginPath(); g.moveTo(px, y); g.lineTo(px, y + h); g.stroke();
    g.textAlign = 'center'; g.fillText(fmtTick(v), px, y + h + 14);
  }
  g.textAlign = 'right'; g.fillText(xlabel, x + w, y + h + 28);
  g.save(); g.translate(12, y + h / 2); g.rotate(-Math.PI / 2); g.textAlign = 'center'; g.fillText(ylabel, 0, 0); g.restore();
}
function fmtTick(v) { const a = Math.abs(v); return Number.isInteger(v) ? String(v) : a >= 1000 || (a < 0.01 && a > 0) ? v.toPrecision(2) : String(+v.toFixed(3)); }

function drawStrip(s) {
  const [g, W, H] = setup($('strip'));
  const box = { x: 56, y: 10, w: W - 56 - 70, h: H - 44 };
  // The window ends now; when the newest return is older than the window
  // (the stream stopped), it ends at that return instead, so the last
  // returns stay on screen.
  const now = serverNow(), newest = s && s.returns.length ? s.returns[s.returns.length - 1].t : now;
  const paused = newest < now - WINDOW_S * 1000;
  const tEnd = paused ? newest + 1000 : now, t0 = tEnd - WINDOW_S * 1000;
  const RIGHT_S = 2; // the axis runs on past "now", so the newest points are not cut in half
  const vis = s ? s.returns.filter((p) => p.t >= t0) : [];
  let lo = Infinity, hi = -Infinity;
  for (const p of vis) { lo = Math.min(lo, p.r - (p.sig || 0)); hi = Math.max(hi, p.r + (p.sig || 0)); }
  if (!Number.isFinite(lo)) { lo = 0; hi = 10; }
  const pad = Math.max((hi - lo) * 0.08, 0.05); lo -= pad; hi += pad;
  axes(g, box, -WINDOW_S, RIGHT_S, lo, hi, paused ? `time, s (0 = ${fmt((now - tEnd) / 1000, 0)} s ago: no returns since)` : 'time, s (0 = now)', 'range, m');
  const px = (t) => box.x + (t - t0) / ((WINDOW_S + RIGHT_S) * 1000) * box.w;
  const py = (r) => box.y + box.h - (r - lo) / (hi - lo) * box.h;
  let plotted = 0;
  for (const p of vis) {
    if (!Number.isFinite(p.r)) continue;
    const x = px(p.t), y = py(p.r), c = snrColour(p.snr);
    g.strokeStyle = c; g.fillStyle = c;
    if (p.sig > 0) {
      const e = Math.max(1, py(p.r - p.sig) - y);
      g.beginPath(); g.moveTo(x, y - e); g.lineTo(x, y + e); g.moveTo(x - 2, y - e); g.lineTo(x + 2, y - e);
      g.moveTo(x - 2, y + e); g.lineTo(x + 2, y + e); g.stroke();
    }
    g.beginPath(); g.arc(x, y, 2.5, 0, 2 * Math.PI); g.fill();
    plotted++;
  }
  // SNR legend
  const lx = box.x + box.w + 20, ly = box.y, lh = box.h * 0.7;
  for (let i = 0; i < lh; i++) { g.fillStyle = snrColour(SNR_MAX_DB - i / lh * (SNR_MAX_DB - SNR_MIN_DB)); g.fillRect(lx, ly + i, 12, 1); }
  g.fillStyle = '#8a96a3'; g.textAlign = 'left';
  g.fillText(`${SNR_MAX_DB} dB`, lx + 16, ly + 8); g.fillText(`${SNR_MIN_DB} dB`, lx + 16, ly + lh); g.fillText('SNR', lx, ly + lh + 16);
  if (!vis.length) { g.fillStyle = '#8a96a3'; g.textAlign = 'center'; g.fillText('no returns in the window', box.x + box.w / 2, box.y + box.h / 2); }
  root.dataset.returnsPlotted = String(plotted);
}

function trace(g, d, x0, xScale, yOf, colour) {
  // d: {bucket, lo, hi?}; x0(index) -> px
  const hi = d.hi || d.lo, n = d.lo.length;
  g.strokeStyle = colour; g.lineWidth = 1;
  g.beginPath();
  let pen = false;
  for (let k = 0; k < n; k++) {
    const a = d.lo[k], b = hi[k];
    if (a === null || b === null || !Number.isFinite(a)) { pen = false; continue; }
    const x = x0 + (k * d.bucket + (d.bucket - 1) / 2) * xScale;
    if (d.bucket === 1) { if (pen) g.lineTo(x, yOf(a)); else g.moveTo(x, yOf(a)); }
    else { if (pen) g.lineTo(x, yOf(a)); else g.moveTo(x, yOf(a)); g.lineTo(x, yOf(b)); }
    pen = true;
  }
  g.stroke();
  return n * (d.hi ? 2 : 1);
}

function range(d) {
  let lo = Infinity, hi = -Infinity;
  for (const v of d.lo) if (v !== null && Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  for (const v of (d.hi || [])) if (v !== null && Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  return Number.isFinite(lo) ? [lo, hi] : [0, 1];
}

function drawWave(s) {
  const [g, W, H] = setup($('wave'));
  const w = s && s.waveform;
  if (!w) {
    g.fillStyle = '#8a96a3'; g.textAlign = 'center';
    g.fillText('a waveform arrives while frames flow (snapshots are taken only while this page is open)', W / 2, H / 2);
    root.dataset.waveformPoints = '0'; root.dataset.waveformReturns = '0'; root.dataset.waveformSeq = '';
    return;
  }
  const ns = (i) => (w.t0_s + i * w.dt_s) * 1e9;
  const xlo = ns(0), xhi = ns(Math.max(1, w.samples - 1));
  const top = { x: 56, y: 10, w: W - 56 - 16, h: (H - 80) * 0.6 };
  const bot = { x: 56, y: top.y + top.h + 34, w: top.w, h: (H - 80) * 0.4 };
  const pxOfIdx = (box, i) => box.x + (ns(i) - xlo) / (xhi - xlo) * box.w;
  const shade = (box, r, colour, label) => {
    if (r[1] <= r[0]) return;
    const a = pxOfIdx(box, r[0]), b = pxOfIdx(box, r[1]);
    g.fillStyle = colour; g.fillRect(a, box.y, b - a, box.h);
    if (label) { g.fillStyle = '#8a96a3'; g.textAlign = 'left'; g.fillText(label, a + 3, box.y + 12); }
  };
  // top: stop channel, volts
  let [vlo, vhi] = range(w.stop_v);
  const vpad = (vhi - vlo) * 0.08 || 0.01; vlo -= vpad; vhi += vpad;
  for (const b of [top, bot]) {
    shade(b, w.gates.pre, 'rgba(138,150,163,0.13)', b === top ? 'noise gate' : '');
    shade(b, w.gates.beyond, 'rgba(138,150,163,0.13)', b === top ? 'noise gate' : '');
    shade(b, w.gates.range, 'rgba(88,166,255,0.08)', b === top ? 'range gate' : '');
  }
  axes(g, top, xlo, xhi, vlo, vhi, '', 'stop, V');
  const yTop = (v) => top.y + top.h - (v - vlo) / (vhi - vlo) * top.h;
  const xScale = top.w / Math.max(1, w.samples - 1);
  // noise mean and ±3σ
  g.setLineDash([4, 4]); g.strokeStyle = '#6e7681';
  for (const v of [w.mean_v, w.mean_v + 3 * w.sigma_v, w.mean_v - 3 * w.sigma_v]) {
    g.beginPath(); g.moveTo(top.x, yTop(v)); g.lineTo(top.x + top.w, yTop(v)); g.stroke();
  }
  g.setLineDash([]);
  g.fillStyle = '#8a96a3'; g.textAlign = 'right'; g.fillText('μ ± 3σ', top.x + top.w - 2, yTop(w.mean_v + 3 * w.sigma_v) - 3);
  let points = trace(g, w.stop_v, top.x, xScale, yTop, '#d8dee4');
  // time reference
  const tref = w.t_ref_s * 1e9;
  if (tref >= xlo && tref <= xhi) {
    const x = top.x + (tref - xlo) / (xhi - xlo) * top.w;
    g.strokeStyle = '#3fb950'; g.setLineDash([2, 3]); g.beginPath(); g.moveTo(x, top.y); g.lineTo(x, top.y + top.h); g.stroke(); g.setLineDash([]);
    g.fillStyle = '#3fb950'; g.textAlign = 'left'; g.fillText('t_ref', x + 3, top.y + top.h - 4);
  }
  // returns
  let marked = 0;
  for (const r of w.returns) {
    const t = r.t_stop_s * 1e9;
    if (!(t >= xlo && t <= xhi)) continue;
    const x = top.x + (t - xlo) / (xhi - xlo) * top.w, c = snrColour(r.snr_db);
    g.strokeStyle = c; g.beginPath(); g.moveTo(x, top.y); g.lineTo(x, top.y + top.h); g.stroke();
    const y = yTop(w.mean_v + r.amplitude_v);
    g.fillStyle = c; g.beginPath(); g.moveTo(x, y - 2); g.lineTo(x - 6, y - 12); g.lineTo(x + 6, y - 12); g.closePath(); g.fill();
    // Labels step down one line per return, so neighbouring returns stay legible.
    g.textAlign = 'left'; g.fillText(`${fmt(r.range_m, 3)} m ± ${fmt(r.range_sigma_m * 100, 1)} cm, ${fmt(r.snr_db, 1)} dB`, x + 8, top.y + 24 + 14 * (marked % 8));
    marked++;
  }
  // bottom: detector output in units of its noise sigma
  let [dlo, dhi] = range(w.detector_sigma);
  if (w.threshold_sigma !== null && w.threshold_sigma !== undefined) dhi = Math.max(dhi, w.threshold_sigma);
  const dpad = (dhi - dlo) * 0.08 || 1; dlo -= dpad; dhi += dpad;
  axes(g, bot, xlo, xhi, dlo, dhi, 'time from trigger, ns', 'detector, σ');
  const yBot = (v) => bot.y + bot.h - (v - dlo) / (dhi - dlo) * bot.h;
  points += trace(g, w.detector_sigma, bot.x, xScale, yBot, '#58a6ff');
  if (w.threshold_sigma !== null && w.threshold_sigma !== undefined) {
    const y = yBot(w.threshold_sigma);
    g.strokeStyle = '#f85149'; g.setLineDash([6, 4]); g.beginPath(); g.moveTo(bot.x, y); g.lineTo(bot.x + bot.w, y); g.stroke(); g.setLineDash([]);
    g.fillStyle = '#f85149'; g.textAlign = 'right'; g.fillText(`threshold ${fmt(w.threshold_sigma, 2)} σ`, bot.x + bot.w - 2, y - 3);
  }
  const dd = w.detector_sigma, dh = dd.hi || dd.lo;
  g.fillStyle = '#f85149';
  for (const i of w.detections) {
    const v = dh[Math.floor(i / dd.bucket)];
    if (v === null || v === undefined) continue;
    g.beginPath(); g.arc(pxOfIdx(bot, i), yBot(v), 3.5, 0, 2 * Math.PI); g.fill();
  }
  $('wave-info').textContent = `(report ${w.seq_first}${w.seq_last !== w.seq_first ? '–' + w.seq_last : ''}, ` +
    `${w.samples} samples shown as ${points} points, ${w.detections.length} detections)`;
  root.dataset.waveformSeq = String(w.seq_last);
  root.dataset.waveformReturns = String(marked);
  root.dataset.waveformPoints = String(points);
}

function drawFaCi(fa, d) {
  const [g, W, H] = setup($('fa-ci'));
  const lg = (p) => Math.log10(Math.max(p, 1e-15));
  const vals = [fa.ci95[1], d.pfa_cell, fa.rate].filter((v) => v > 0).map(lg);
  const hiL = Math.ceil(Math.max(...vals, -1)), loL = Math.floor(Math.min(lg(d.pfa_cell), lg(fa.ci95[1])) - 1);
  const x = (p) => 8 + (lg(p) - loL) / (hiL - loL) * (W - 16);
  g.fillStyle = fa.excess ? '#f85149' : '#3fb950';
  const a = fa.ci95[0] > 0 ? x(fa.ci95[0]) : 8;
  g.fillRect(a, 8, Math.max(2, x(fa.ci95[1]) - a), 8);
  g.fillStyle = '#d8dee4';
  g.fillRect(x(d.pfa_cell) - 1, 3, 2, 18);
  g.fillStyle = '#8a96a3'; g.textAlign = 'left'; g.fillText(`1e${loL}`, 0, H - 1); g.textAlign = 'right'; g.fillText(`1e${hiL}  | design`, W, H - 1);
}

// ---------------------------------------------------------------- loop
function draw() {
  const s = state.sensors.get(state.selected);
  renderText();
  drawStrip(s);
  drawWave(s);
  // Report-to-screen delay of every report drawn now.
  const now = serverNow();
  for (const x of state.sensors.values()) {
    for (const t of x.pending) {
      const dly = now - t;
      state.lastDelayMs = dly;
      if (dly > state.maxDelayMs) state.maxDelayMs = dly;
    }
    x.pending.length = 0;
  }
  root.dataset.reports = String(state.reports);
  root.dataset.maxDelayMs = String(Math.round(state.maxDelayMs));
}

$('window-s').textContent = WINDOW_S;
let lastFull = 0;
function frame() {
  const t = performance.now();
  // New data: draw now; otherwise twice a second so the strip chart scrolls.
  if (state.dirty || t - lastFull > 500) { state.dirty = false; lastFull = t; draw(); }
  requestAnimationFrame(frame);
}
connect();
requestAnimationFrame(frame);
