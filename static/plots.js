// The live plots: uPlot (static/vendor/, MIT) charts fed by WS /ws/plots.
//
// The server (app/server/gui/plots.py, PlotFeed) sends the whole window once, then only
// the new points, up to 20 times a second; each message is appended to the rings kept
// here (the last `span` seconds) and every chart is redrawn into its existing canvas
// (uPlot's setData: the chart, its canvas and its scales stay). One clock for every chart:
// x is seconds since the stream started and all charts show the same window. The legend
// under each title shows the newest values (the hovered ones while the mouse is over a
// chart); an empty chart says why beside its axes.
"use strict";

(function () {
  const FONT = "12px system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif";
  const GREY = "#7f7f7f";
  const NIS_GATE_COLORS = ["#1f77b4", "#9467bd"];

  const fmtFixed = (d) => (v) => (v === null || v === undefined || !isFinite(v) ? "–" : v.toFixed(d));
  const fmtSig = (v) => (v === null || v === undefined || !isFinite(v) ? "–" : (v >= 100 ? v.toFixed(0) : Number(v.toPrecision(2)).toString()));

  // A series measured once per Kalman update (NIS) is joined across the bins without one
  // (an update every other bin, a phone's 10 Hz magnetometer) but not across a gap longer
  // than this (s): a field refused as disturbed (a magnet) lasts at least
  // mag_min_undisturbed (0.5 s) and shows as a break in the line, not as a long diagonal.
  const JOIN_S = 0.4;

  // The charts: key, title (with unit), series (label, colour, dashed, span, width, role),
  // the unit and format of the legend's values, and the y scale. span: true joins every gap
  // (a constant line sent as its two ends), a number (s) joins the gaps shorter than that.
  // role: "data" (counts for "has data"), "band" (a gate's constant line), "marker" (injected).
  const SPECS = [
    // the phone's own angles (dashed) are told in their estimate's legend item: "yaw 12.3° (phone 12.0°)"
    { key: "euler", title: "Euler angles [°]", unit: "°", fmt: fmtFixed(1), pairs: { 0: 3, 1: 4, 2: 5 }, series: [
      ["yaw", "#d62728", false], ["pitch", "#2ca02c", false], ["roll", "#1f77b4", false],
      ["phone yaw", "#d62728", true, false, 1.5, undefined, null], ["phone pitch", "#2ca02c", true, false, 1.5, undefined, null],
      ["phone roll", "#1f77b4", true, false, 1.5, undefined, null]] },
    // against the phone's own estimate is a difference, not an error: that estimate is
    // itself degrees off on real phones
    { key: "error", title: "Angle to truth, to the phone's own [°]", unit: "°", fmt: fmtFixed(2), series: [
      ["vs phone's own", "#ff7f0e", false], ["to truth", "#17becf", false]] },
    { key: "acc", title: "|acc| [m/s²]", unit: " m/s²", fmt: fmtFixed(2), series: [
      ["|acc|", "#1f77b4", false], ["band lo", GREY, true, true, 1.5, "band", "gate band"], ["band hi", GREY, true, true, 1.5, "band", null],
      ["shake injected", "#d62728", false, false, 4, "marker"]] },
    { key: "mag", title: "|mag|, L_k [µT]", unit: " µT", fmt: fmtFixed(1), series: [
      ["|mag|", "#9467bd", false], ["L_k", "#e377c2", false], ["band lo", GREY, true, true, 1.5, "band", "gate band"],
      ["band hi", GREY, true, true, 1.5, "band", null], ["magnet injected", "#d62728", false, false, 4, "marker"]] },
    { key: "nis", title: "NIS (log scale)", unit: "", fmt: fmtSig, log: true, series: [
      ["acc NIS", "#1f77b4", false, JOIN_S], ["mag NIS", "#9467bd", false, JOIN_S],
      ["acc gate", NIS_GATE_COLORS[0], true, true, 1.5, "band"], ["mag gate", NIS_GATE_COLORS[1], true, true, 1.5, "band"]] },
  ];

  // ------------------------------------------------------------------ the data
  const RINGS = { pose: 9, acc: 3, mag: 4 };   // columns per ring (x first), as the server sends
  const store = { rings: {}, meta: { span: 20, spans: [], why: {} }, now: null };
  const win = { lo: 0, hi: 20 };
  const stats = { messages: 0, bytes: 0, redraws: {}, snapshots: 0 };

  function clearRings() {
    for (const [name, n] of Object.entries(RINGS)) store.rings[name] = Array.from({ length: n }, () => []);
  }
  clearRings();

  function append(name, cols) {
    if (!cols || !cols.length || !cols[0].length) return;
    const ring = store.rings[name];
    for (let c = 0; c < ring.length; c++) {
      const dst = ring[c], src = cols[c];
      for (let i = 0; i < src.length; i++) dst.push(src[i]);
    }
  }

  function trim() {
    const from = win.lo - 0.5;
    for (const ring of Object.values(store.rings)) {
      const x = ring[0];
      let k = 0;
      while (k < x.length && x[k] < from) k++;
      if (k > 0) for (const col of ring) col.splice(0, k);
    }
  }

  function setWindow() {
    const span = store.meta.span || 20;
    const now = store.now === null ? 0 : store.now;
    win.hi = Math.max(span, now);
    win.lo = win.hi - span;
  }

  // ------------------------------------------------------------------ per-chart columns
  function unwrapDeg(col, maxSpan = 540) {
    // yaw and roll (±180°) unwrapped over the window, shifted by whole turns so that the
    // newest value lies in [-180, 180]; a column that turned more than maxSpan stays in
    // ±180 with a gap where it wraps (as app/server/gui/plots.py's unwrap_deg)
    const out = col.slice();
    let prev = null, off = 0, last = -1, lo = Infinity, hi = -Infinity;
    for (let i = 0; i < col.length; i++) {
      const v = col[i];
      if (v === null) continue;
      if (prev !== null) off -= 360 * Math.round((v + off - prev) / 360);
      out[i] = prev = v + off;
      last = i;
    }
    if (last < 0) return out;
    const shift = 360 * Math.round(out[last] / 360);
    for (let i = 0; i < out.length; i++) if (out[i] !== null) {
      out[i] -= shift;
      lo = Math.min(lo, out[i]); hi = Math.max(hi, out[i]);
    }
    if (hi - lo <= maxSpan) return out;
    const br = col.slice();
    let p = null;
    for (let i = 0; i < col.length; i++) {
      if (col[i] === null) continue;
      if (p !== null && Math.abs(col[i] - p) > 180) br[i] = null;
      p = col[i];
    }
    return br;
  }

  function alignDeg(col, ref) {
    // the same angle of another source (the phone's own yaw or roll beside the estimate's):
    // each value shifted by whole turns to lie nearest the reference's at the same time, so
    // two values 5° apart are drawn 5° apart. Unwrapped alone, through pitch ±90° (where
    // yaw and roll jump by 180°) the two could unwrap in opposite directions, a turn apart
    // (as app/server/gui/plots.py's unwrap_deg with align)
    const out = col.slice();
    for (let i = 0; i < out.length; i++) {
      const r = ref[i];
      if (out[i] !== null && r !== null && r !== undefined) out[i] -= 360 * Math.round((out[i] - r) / 360);
    }
    return out;
  }

  function ends(n, v) {
    const out = new Array(n).fill(null);
    if (v !== null && v !== undefined && n > 0) { out[0] = v; out[n - 1] = v; }
    return out;
  }

  function during(x, y, kind) {
    const spans = (store.meta.spans || []).filter((s) => s[0] === kind);
    if (!spans.length) return new Array(x.length).fill(null);
    return x.map((t, i) => (spans.some(([, a, b]) => t >= a && (b === null || t <= b)) ? y[i] : null));
  }

  function columns(key) {
    const m = store.meta, r = store.rings;
    if (key === "euler" || key === "error") {
      const p = r.pose;
      if (key === "error") return [p[0], p[7], p[8]];
      const yaw = unwrapDeg(p[1]), roll = unwrapDeg(p[3]);
      return [p[0], yaw, p[2], roll, alignDeg(unwrapDeg(p[4]), yaw), p[5], alignDeg(unwrapDeg(p[6]), roll)];
    }
    if (key === "acc") {
      const a = r.acc, n = a[0].length, band = m.acc_band || [null, null];
      return [a[0], a[1], ends(n, band[0]), ends(n, band[1]), during(a[0], a[1], "shake")];
    }
    if (key === "mag") {
      const g = r.mag, n = g[0].length, band = m.mag_band || [null, null];
      return [g[0], g[1], g[2], ends(n, band[0]), ends(n, band[1]), during(g[0], g[1], "magnet")];
    }
    // NIS: acc and mag rows merged on one time axis, each null at the other's times (joined: JOIN_S)
    const a = r.acc, g = r.mag, x = [], na = [], nm = [];
    let i = 0, j = 0;
    while (i < a[0].length || j < g[0].length) {
      if (j >= g[0].length || (i < a[0].length && a[0][i] <= g[0][j])) { x.push(a[0][i]); na.push(a[2][i]); nm.push(null); i++; }
      else { x.push(g[0][j]); na.push(null); nm.push(g[3][j]); j++; }
    }
    return [x, na, nm, ends(x.length, m.acc_gate), ends(x.length, m.mag_gate)];
  }

  // ------------------------------------------------------------------ the charts
  const charts = {};

  function lastFinite(col, upTo) {
    for (let i = Math.min(upTo, col.length - 1); i >= 0; i--) if (col[i] !== null && isFinite(col[i])) return col[i];
    return null;
  }

  // the legend's "now" value: the newest finite one, if it is news (a sensor that stopped
  // while the stream goes on has its last value seconds behind: "–", not a live figure;
  // how far behind is the server's meta.stale_s)
  function newest(x, col) {
    const stale = store.meta.stale_s;       // none before the first meta: not judged
    for (let i = col.length - 1; i >= 0; i--) {
      if (col[i] !== null && isFinite(col[i])) {
        return stale !== undefined && store.now !== null && x[i] !== undefined
          && x[i] < store.now - stale ? null : col[i];
      }
    }
    return null;
  }

  function decades(min, max) {
    const out = [];
    if (!(min > 0) || !(max > 0)) return out;
    for (let e = Math.ceil(Math.log10(min) - 1e-9); e <= Math.floor(Math.log10(max) + 1e-9); e++) out.push(10 ** e);
    return out;
  }

  // uPlot's gaps hook for a series that does not span gaps: it gets the null runs as pixel
  // ranges from the point before each run to the point after it, and draws a break for those
  // it returns. The runs shorter than `s` seconds of the x scale are joined.
  function joinShorter(s) {
    return (u, sidx, i0, i1, gaps) => {
      const span = u.scales.x.max - u.scales.x.min;
      if (!(span > 0)) return gaps;
      const px = s * u.bbox.width / span;
      return gaps.filter(([a, b]) => b - a > px);
    };
  }

  function build(spec, root) {
    const card = document.createElement("div");
    card.className = "plot";
    card.id = "plot-" + spec.key;
    card.innerHTML = `<div class="plot-head"><span class="plot-title"></span><span class="legend"></span></div>` +
      `<div class="plot-body"><div class="plot-why" hidden></div></div>`;
    card.querySelector(".plot-title").textContent = spec.title;      // text, never markup
    root.appendChild(card);
    const legend = card.querySelector(".legend"), body = card.querySelector(".plot-body");
    const items = spec.series.map(([label, color, dash, , width, role, name]) => {
      const el = document.createElement("span");
      el.hidden = name === null;                    // drawn, but told by its pair's item
      el.className = "li" + (role ? " " + role : "");
      el.innerHTML = `<i style="border-top:${width && width > 2 ? 4 : 2}px ${dash ? "dashed" : "solid"} ${color}"></i>` +
        `<span class="name"></span> <b class="val">–</b>`;
      el.querySelector(".name").textContent = name || label;
      legend.appendChild(el);
      return el;
    });
    const chart = { spec, card, body, items, why: card.querySelector(".plot-why"), u: null };
    const opts = {
      width: Math.max(100, body.clientWidth), height: Math.max(60, body.clientHeight),
      legend: { show: false },
      cursor: { drag: { x: false, y: false }, points: { show: false } },
      padding: [10, 10, 0, 2],            // room for the top tick label (not cut)
      scales: { x: { time: false, range: () => [win.lo, win.hi] },
                y: spec.log ? { distr: 3, log: 10 } : { auto: true } },
      axes: [
        { font: FONT, size: 22, gap: 2, ticks: { size: 4 }, stroke: "#333", grid: { stroke: "#e4e4e4" },
          space: 36, incrs: [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000] },
        { font: FONT, size: 46, gap: 3, space: 18, ticks: { size: 4 }, stroke: "#333", grid: { stroke: "#e4e4e4" },
          ...(spec.log ? {                 // decades only (no minor lines)
            splits: (u, ai, min, max) => decades(min, max),
            // 1e4 and up as powers (a shake's or a magnet's NIS: "100000" did not fit the axis)
            values: (u, vals) => vals.map((v) => (v === null ? "" : v >= 1e4 ? `1e${Math.round(Math.log10(v))}`
              : v >= 1 ? v.toFixed(0) : String(Number(v.toPrecision(1))))),
          } : {}) },
      ],
      series: [{ label: "t [s]" }].concat(spec.series.map(([label, color, dash, span, width]) => ({
        label, stroke: color, width: width || 1.5, dash: dash ? [6, 4] : undefined, spanGaps: span === true,
        ...(typeof span === "number" ? { gaps: joinShorter(span) } : {}),
        points: { show: false } }))),
      hooks: { setCursor: [(u) => { if (chart.u) legendAt(chart, u.cursor.idx); }] },
    };
    chart.u = new uPlot(opts, spec.series.reduce((d) => d.concat([[]]), [[]]), body);
    new ResizeObserver(() => {
      const w = body.clientWidth, h = body.clientHeight;
      if (w > 0 && h > 0 && (w !== chart.u.width || h !== chart.u.height)) chart.u.setSize({ width: w, height: h });
    }).observe(body);
    stats.redraws[spec.key] = 0;
    charts[spec.key] = chart;
  }

  function legendAt(chart, idx) {
    const { u, spec, items } = chart;
    const hover = idx !== null && idx !== undefined;
    spec.series.forEach(([label, , dash, , , role, name], k) => {
      const col = u.data[k + 1] || [];
      const v = hover ? col[idx] : newest(u.data[0] || [], col);
      const el = items[k];
      if (name === null) return;
      let txt;
      if (role === "band") {          // a gate: its value (a band: both ends), or "off"
        const g = lastFinite(col, col.length - 1);
        const hi = name ? lastFinite(u.data[k + 2] || [], Infinity) : null;
        txt = g === null ? "off" : spec.fmt(g) + (hi !== null ? "–" + spec.fmt(hi) : "") + spec.unit;
      } else if (role === "marker") {
        txt = "";
        el.hidden = !(store.meta.spans || []).some((s) => s[0] === (spec.key === "acc" ? "shake" : "magnet"));
      } else {
        txt = v === null || v === undefined ? "–" : spec.fmt(v) + spec.unit;
        const pair = spec.pairs ? spec.pairs[k] : undefined;
        if (pair !== undefined) {         // the phone's own value beside the estimate's
          const pc = u.data[pair + 1] || [];
          const pv = hover ? pc[idx] : newest(u.data[0] || [], pc);
          if (pv !== null && pv !== undefined) txt += ` (phone ${spec.fmt(pv)}${spec.unit})`;
        }
        // a series with nothing in the window (the phone's own angles without ORI, L_k of
        // an estimator without it) is left out, unless the whole chart is empty
        el.hidden = lastFinite(col, Infinity) === null && !chart.card.classList.contains("empty");
      }
      const b = el.querySelector(".val");
      if (b.textContent !== txt) b.textContent = txt;
    });
  }

  function redraw() {
    redraw.pending = false;
    setWindow();
    trim();
    const tline = document.getElementById("plots-now");
    if (tline) tline.textContent = store.now === null ? "–" : store.now.toFixed(1) + " s";
    for (const chart of Object.values(charts)) {
      if (!chart.body.offsetParent) continue;       // not on show (another tab)
      const data = columns(chart.spec.key);
      chart.u.setData(data);
      stats.redraws[chart.spec.key]++;
      const has = chart.spec.series.some(([, , , , , role], k) => !role && data[k + 1].some((v) => v !== null));
      const why = (store.meta.why || {})[chart.spec.key] || "";
      chart.why.hidden = has;
      const text = has ? "" : "Empty: " + why + ".";
      if (chart.why.textContent !== text) chart.why.textContent = text;
      chart.card.classList.toggle("empty", !has);
      if (chart.u.cursor.idx === null || chart.u.cursor.idx === undefined) legendAt(chart, null);
    }
  }

  function schedule() {
    // a task, not an animation frame: the 3D view beside may hold frames back (software
    // WebGL), and the charts must keep up with the stream; messages that arrive together
    // are drawn once
    if (redraw.pending) return;
    redraw.pending = true;
    setTimeout(() => { try { redraw(); } catch (e) { console.error(e); } }, 0);
  }

  // ------------------------------------------------------------------ the stream
  function onMessage(ev) {
    stats.messages++;
    stats.bytes += ev.data.length;
    const msg = JSON.parse(ev.data);
    if (msg.k === "s") { clearRings(); store.now = null; stats.snapshots++; }
    if (msg.meta) Object.assign(store.meta, msg.meta);
    for (const name of Object.keys(RINGS)) append(name, msg[name]);
    if (msg.now !== null && msg.now !== undefined) store.now = msg.k === "s" ? msg.now : Math.max(store.now ?? -Infinity, msg.now);
    schedule();
  }

  function connect() {
    const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws/plots`);
    ws.onmessage = onMessage;
    ws.onclose = () => setTimeout(connect, 1000);
  }

  function init() {
    const root = document.getElementById("plots");
    if (!root || typeof uPlot === "undefined") return;
    for (const spec of SPECS) build(spec, root);
    connect();
    // a panel shown again (its tab) draws at once
    new ResizeObserver(schedule).observe(root);
  }

  window.orientlabPlots = { charts, store, win, stats, columns };
  init();
})();
