// Embed the viser viewer (same host, its own port); the Plots tab (static/plots.js); the
// Connect tab (presenter only): how each app reaches this PC, with QR codes, and the
// phone's status.
let presenter = false;
const $ = (id) => document.getElementById(id);

// Whose page this is (presenter or watcher) and where the viewer is. A classroom Wi-Fi drops
// requests: asked again until it answers, the badge saying so meanwhile (until then the
// page shows neither the presenter's part nor the watcher's note).
async function whoami() {
  for (let wait = 500; ; wait = Math.min(2 * wait, 5000)) {
    try {
      const r = await fetch("/api/info");
      if (r.ok) return await r.json();
    } catch (e) { /* dropped: ask again */ }
    $("source").textContent = "server not reachable";
    $("source").className = "badge warn";
    await new Promise((done) => setTimeout(done, wait));
  }
}

async function init() {
  const info = await whoami();
  presenter = info.presenter;
  // no token in the viewer's address (the link is on the projector): its WebSocket carries
  // the presenter's cookie, which is this host's whatever the port
  const url = `${location.protocol}//${location.hostname}:${info.viewer_port}/`;
  document.body.classList.toggle("watch-only", !presenter);
  $("viewer").src = url;
  $("viewer-link").href = url;
  $("watch-note").hidden = presenter;
  $("watch-badge").hidden = presenter;      // the Plots tab opens by itself: said on every tab
  $("presenter-connect").hidden = !presenter;
  tabs(".tabs [role=tab]", (b) => { tabPicked = true; showPanel(b); });
  tabs(".apps [role=tab]", (b) => { appPicked = true; showApp(b); });
  if (presenter) {
    for (const img of document.querySelectorAll("img.qr")) img.src = `/api/connect/qr/${img.dataset.qr}.svg`;
    $("release").onclick = () => post("/api/phone", { release: true });
    $("lock").onclick = () => post("/api/phone", { locked: $("lock").dataset.locked !== "true" });
    $("sl-convention").onchange = (e) => post("/api/sensorlogger/convention", { convention: e.target.value });
    $("poll-form").onsubmit = (e) => { e.preventDefault(); post("/api/phyphox/poll", { url: $("poll-url").value }); };
    connect();
  }
  poll();
}

// The aside's tabs: Connect first while nothing streams; once a stream is on, the
// Plots tab (static/plots.js), unless a tab was picked by hand.
let tabPicked = false;
function showPanel(b) {
  for (const o of document.querySelectorAll(".tabs [role=tab]")) o.setAttribute("aria-selected", String(o === b));
  for (const p of document.querySelectorAll("aside > section")) p.hidden = p.id !== b.dataset.panel;
  recordings();
}

// The Recordings tab: each recording's files to download (anyone who sees the page may:
// a class shares its recordings), asked again every few seconds while the tab is shown.
// The list is rebuilt only when it changed (a link keeps its focus); the one being
// recorded offers its log so far, its estimates once it stops (a compressed file is
// whole only then). Names are text, never markup.
const FILES = [["log", "log", "the stream as the Sensor Fusion app logs it"],
  ["estimates", "has_estimates", "every filter's estimate (CSV, gzip)"],
  ["events", "has_events", "the settings it began with and every change (JSON lines)"],
  ["state", "has_state", "the filters' state as it began (npz)"]];
function recordingItem(rec, now) {
  const li = document.createElement("li");
  const name = document.createElement("b");
  name.textContent = rec.name;
  const live = rec.name === now;
  const what = [new Date(rec.modified * 1000).toLocaleString(),
    rec.segment > 1 ? `part ${rec.segment} of ${rec.recording}` : null,
    rec.seconds !== null ? span(rec.seconds) : null,
    rec.samples !== null ? `${rec.samples} samples` : null,
    live ? null : `${(rec.bytes / 1e6).toFixed(rec.bytes < 1e6 ? 2 : 1)} MB`,
    live ? "recording… (the log so far; the estimates when it stops)"
      : (rec.cut_short ? "log cut short" : (rec.complete ? null : "not ended"))];
  const info = document.createElement("span");
  info.className = "detail";
  info.textContent = " " + what.filter((x) => x).join(" · ") + " ";
  if (rec.cut_short) info.title = rec.cut_short;
  li.append(name, info);
  for (const [file, has, title] of FILES) {
    if ((has !== "log" && !rec[has]) || (live && file === "estimates")) continue;
    const a = document.createElement("a");
    a.href = `/api/recordings/${encodeURIComponent(rec.name)}/${file}`;
    a.download = "";
    a.textContent = file;
    a.title = title;
    a.dataset.file = file;
    li.append(a, " ");
  }
  return li;
}
async function recordings() {
  clearTimeout(recordings.timer);
  if ($("panel-recordings").hidden) return;
  try {
    const r = await fetch("/api/recordings");
    if (!r.ok) throw new Error(r.statusText);
    const v = await r.json();
    const st = v.status || {};
    // the segment being written: a recording goes on in NAME_2... when a new stream starts
    const segs = st.segments || [];
    const now = st.recording ? (segs.length ? segs[segs.length - 1].name : st.name) : null;
    const recs = v.recordings.map((x) => x.name === now ? { ...x, bytes: 0, modified: 0 } : x);
    const key = JSON.stringify([now, recs, v.left_out, v.folder]);
    if (key !== recordings.shown) {
      recordings.shown = key;
      const n = v.recordings.length;
      $("recordings-status").textContent = (now ? `recording ${now} now · ` : "")
        + `${n} recording${n === 1 ? "" : "s"} in the folder ${v.folder}`;
      $("recordings").replaceChildren(...v.recordings.map((x) => recordingItem(x, now)));
      $("recordings-left").replaceChildren(...(v.left_out || []).map((x) => {
        const li = document.createElement("li");
        li.textContent = `${x.file}: ${x.why}`;
        return li;
      }));
      $("recordings-left-note").hidden = !(v.left_out || []).length;
    }
  } catch (e) {
    $("recordings-status").textContent = "server not reachable";
    recordings.shown = null;
  }
  recordings.timer = setTimeout(recordings, 3000);
}

// The Connect tab's app: the streaming phone's, until the presenter picks one
let appPicked = false, appShownFor = null;
const APP_TAB = { sensorlogger: "sensorlogger", phyphox: "phyphox", "phyphox-poll": "phyphox", sensorfusion: "sensorfusion" };
function showApp(b) {
  for (const o of document.querySelectorAll(".apps [role=tab]")) o.setAttribute("aria-selected", String(o === b));
  for (const a of document.querySelectorAll(".app")) a.hidden = a.id !== "app-" + b.dataset.app;
}

function tabs(selector, show) {
  const buttons = document.querySelectorAll(selector);
  for (const b of buttons) b.onclick = () => {
    for (const o of buttons) o.setAttribute("aria-selected", String(o === b));
    show(b);
  };
}

async function post(path, body) {
  const r = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  if (!r.ok) {
    const j = await r.json().catch(() => ({}));
    const msg = Array.isArray(j.detail) ? j.detail.map((d) => d.msg).join("; ") : (j.detail || r.statusText);
    $("phone-status").textContent = "refused: " + msg;
  }
  connect();
}

const fmt = (x, d = 0) => (x === null || x === undefined ? "–" : Number(x).toFixed(d));

function span(s) {  // a duration in words: 3.2 s, 4 min, 2 h, 413 d
  const a = Math.abs(s), sign = s < 0 ? "−" : "";
  if (a < 120) return sign + a.toFixed(a < 10 ? 1 : 0) + " s";
  if (a < 7200) return sign + (a / 60).toFixed(0) + " min";
  if (a < 172800) return sign + (a / 3600).toFixed(1) + " h";
  return sign + (a / 86400).toFixed(0) + " d";
}

const PLATFORM = { android: "Android", ios: "iPhone" };
const SENSOR_NAMES = { ACC: "Accelerometer", GYR: "Gyroscope", MAG: "Magnetometer" };
const CONVENTION = { android: "Android signs", ios: "Standardise off", "ios-standardised": "Standardise on" };

// Every string from a phone or the network (a phone's model, its label, an app's reason) is
// text, never markup: the status is built as HTML for its <b> and <br> only.
function esc(x) {
  return String(x ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

function describe(v) {
  const slot = v.slot, s = v.stream, lines = [];
  const http = v.http.streams.find((x) => x.holder) || null;
  if (slot.holder) {
    let who = `<b>${esc(slot.holder.app_name)}</b>`;
    if (http && http.platform && http.platform !== "unknown") who += ` · ${esc(PLATFORM[http.platform] || http.platform)}`;
    if (http && http.convention && http.app === "sensorlogger") who += ` (${esc(CONVENTION[http.convention] || http.convention)}, ${esc(http.convention_source)})`;
    if (http && (http.model || http.device_model)) who += ` · ${esc(http.model || http.device_model)}`;
    lines.push(`${who} · streaming ${esc(span(slot.holder.for_s))}`);
    // what to change for a right pose (a sensor missing for the tilt, a guessed convention)
    for (const h of (http && http.holder && http.hints) || []) lines.push(`<b>${esc(h)}</b>`);
    const bad = http && http.holder ? Object.entries(http.invalid || {}) : [];
    if (bad.length) lines.push("readings refused: " + bad.map(([k, n]) => `${esc(k)} ${esc(n)}`).join(", "));
    // silent by the slot's own rule (slot.busy): from then on another phone may take over
    lines.push(slot.busy ? `last data ${esc(span(slot.holder.silent_s))} ago`
      : `<b>silent for ${esc(span(slot.holder.silent_s))}</b>` + (slot.locked ? "" : ": another phone may take over"));
  } else {
    lines.push(s.kind === "phone" ? `last phone: ${esc(s.label)} (${esc(s.close_reason || "ended")})` : "no phone: " + esc(s.kind || "waiting"));
  }
  if (http && http.orientation) {
    const o = http.orientation;
    lines.push("phone's own orientation: " + esc(typeof o === "string" ? o : (o.message || o.state)));
  }
  if (s.kind === "phone" && s.rates_hz) {
    const r = Object.entries(s.rates_hz).filter(([k]) => ["ACC", "GYR", "MAG", "ORI"].includes(k));
    const held = Object.keys(s.withheld || {}).map((k) => `${esc(k)} <b>held back</b>`);
    if (r.length || held.length) lines.push("rates: " + r.map(([k, x]) => x === 0 ? `${esc(k)} <b>stopped</b>` : `${esc(k)} ${esc(fmt(x))} Hz`).concat(held).join(" · "));
    // a phone app sends only the sensors ticked in it: the ones that never came, named
    const missing = (s.missing || []).map((k) => SENSOR_NAMES[k] || k);
    if (missing.length) lines.push(`<b>no ${esc(missing.join(", no "))}: tick ${missing.length > 1 ? "them" : "it"} in the app</b>`);
  }
  if (s.kind === "phone") {
    const parts = [];
    if (http) parts.push(`gaps ${esc(http.gaps ?? 0)}`, `out of order ${esc(http.out_of_order ?? 0)}`, `duplicates ${esc(http.duplicates ?? 0)}`);
    parts.push(`late ${esc(s.late)}`, `malformed ${esc(s.malformed)}`);
    lines.push(parts.join(" · "));
  }
  if (http && http.clock_offset_s !== undefined && http.clock_offset_s !== null) lines.push(`phone clock − PC clock: ${esc(span(http.clock_offset_s))}`);
  if (slot.locked) lines.push("<b>slot locked</b>: no new phone is accepted");
  // the phones turned away in the last minute, each once: which one waits, and why
  const away = slot.turned_away || [];
  for (const t of away) lines.push(`turned away: ${esc(t.app_name)} from ${esc(t.who)} · ${esc(t.times)}×, ${esc(span(t.ago_s))} ago: ${esc(String(t.why || "").replace(/^orientlab: /, ""))}`);
  // once no phone waits, the count only: the last reason would read as news (a phone
  // "streaming" that left long ago)
  if (slot.refused && !away.length) lines.push(`refused ${esc(slot.refused)}× in all`);
  return lines.join("<br>");
}

async function connect() {
  try {
    const r = await fetch("/api/connect");
    if (!r.ok) throw new Error(r.statusText);
    const v = await r.json();
    $("sl-url").textContent = v.sensor_logger.url;
    $("px-url").textContent = v.phyphox.push_url;
    $("sf-host").textContent = v.sensorfusion.host;
    $("sf-port").textContent = v.sensorfusion.port;
    $("phone-status").innerHTML = describe(v);
    $("lock").textContent = v.slot.locked ? "Unlock slot" : "Lock slot";
    $("lock").dataset.locked = String(v.slot.locked);
    $("release").disabled = !v.slot.holder;
    const app = v.slot.holder ? APP_TAB[v.slot.holder.app] : null;
    if (app && !appPicked && app !== appShownFor) {
      const b = document.querySelector(`.apps [data-app="${app}"]`);
      if (b) showApp(b);
      appShownFor = app;
    }
    const sl = v.http.streams.find((x) => x.app === "sensorlogger");
    const conv = sl && (sl.convention === "android" ? "Android" : `iPhone, ${CONVENTION[sl.convention] || sl.convention}`);
    $("sl-detected").textContent = sl ? `in force: ${conv} (${sl.convention_source}${sl.reasons && sl.reasons.length ? ": " + sl.reasons.join("; ") : ""})` : "";
    if (document.activeElement !== $("sl-convention")) $("sl-convention").value = v.http.sensorlogger_convention;
    const p = v.http.poll;
    $("poll-status").textContent = p ? `${p.url}: ${p.status || p.state}${p.last_error ? " (" + p.last_error + ")" : ""}` : "";
    $("other-hosts").textContent = v.other_hosts.length
      ? `This PC's other addresses (if the phone is on that network): ${v.other_hosts.join(", ")}.` : "";
    $("unreachable").textContent = v.unreachable || "";
    $("unreachable").hidden = !v.unreachable;
  } catch (e) {
    $("phone-status").textContent = "server not reachable";
  }
  clearTimeout(connect.timer);
  connect.timer = setTimeout(connect, 1000);
}

async function poll() {
  const badge = $("source");
  try {
    const st = await (await fetch("/api/state")).json();
    badge.textContent = st.status;
    // the whole status on hover: a narrow header cuts the badge short
    badge.title = st.status + (presenter ? "" : "\nwatch-only: the presenter's link holds the token that allows changes");
    // a phone connected but silent (its status says so) is a warning, not a live stream
    const silent = st.silent_s !== null && st.silent_s !== undefined;
    badge.className = "badge" + (st.source === "phone" && !silent ? " phone"
      : st.source === "phone-disconnected" || silent ? " warn" : "");
    if (!tabPicked && st.t !== null && st.t !== undefined && $("tab-plots").getAttribute("aria-selected") !== "true") showPanel($("tab-plots"));
    if (!poll.ready) {  // the first start compiles the filters: which are ready
      const h = await (await fetch("/api/health")).json();
      poll.ready = h.ready !== false;
      $("filters").textContent = "filters: " + Object.entries(h.filters || {}).map(([n, s]) => `${n} ${s}${s === "ready" || s === "failed" ? "" : "…"}`).join(", ");
      $("filters").hidden = poll.ready;
    }
  } catch (e) {
    badge.textContent = "server not reachable";
    badge.className = "badge warn";
  }
  setTimeout(poll, 1000);
}
init();
