// magnet dashboard: fleet table and device view, fed by server-sent events (/api/stream).
"use strict";

const S = {
  rows: new Map(),          // device -> row (JSON from the server)
  trs: new Map(),           // device -> {tr, cells}
  sortKey: "device", sortDesc: false, filter: "",
  order: [], orderAt: 0, dirty: false,
  device: null, detail: null, source: null,
  token: null, cloudMode: "proj", plotAt: 0, plotCost: 0,
  stats: {events: 0, rowsApplied: 0, renders: 0, lastEventMs: 0, eventsPerSec: 0, rowsPerSec: 0,
          renderMs: 0, window: []},
};
window.magnetStats = S.stats;
window.magnetRows = S.rows;

const $ = (id) => document.getElementById(id);
const fmt = (v, d = 1) => (v == null || !isFinite(v) ? "\u2013" : Number(v).toFixed(d));
const esc = (s) => String(s == null ? "" : s).replace(/[&<>"']/g, (c) =>
  ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"})[c]);
const deg = (v, d = 1) => (v == null ? "\u2013" : `${fmt(v, d)}\u00b0`);

// ------------------------------------------------------------------------------------------------ token
function takeToken() {
  const params = new URLSearchParams(location.search);
  if (params.has("token")) {
    sessionStorage.setItem("magnet-token", params.get("token"));
    params.delete("token");
    const rest = params.toString();
    history.replaceState(null, "", location.pathname + (rest ? `?${rest}` : "") + location.hash);
  }
  S.token = sessionStorage.getItem("magnet-token");
  $("token").value = S.token || "";
  $("token-row").classList.toggle("hidden", !!S.token);
  $("token").addEventListener("change", () => {
    S.token = $("token").value.trim() || null;
    if (S.token) sessionStorage.setItem("magnet-token", S.token);
  });
}

// ------------------------------------------------------------------------------------------------ stream
// The stream is read with fetch (not EventSource) so that the token goes in a header, never in the address.
async function connect() {
  if (S.source) S.source.abort();
  const source = new AbortController();
  S.source = source;
  const params = new URLSearchParams();
  if (S.device) params.set("device", S.device);
  try {
    const res = await fetch(`/api/stream?${params}`, {headers: authHeaders(), signal: source.signal});
    if (!res.ok || !res.body) throw new Error(`HTTP ${res.status}`);
    setConn(true);
    const reader = res.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = "";
    for (;;) {
      const {value, done} = await reader.read();
      if (done) break;
      buffer += value;
      let cut;
      while ((cut = buffer.indexOf("\n\n")) >= 0) {
        onEvent(buffer.slice(0, cut));
        buffer = buffer.slice(cut + 2);
      }
    }
  } catch (e) {
    if (source.signal.aborted) return;
  }
  if (source.signal.aborted) return;
  setConn(false);
  S.stats.streamErrors = (S.stats.streamErrors || 0) + 1;
  setTimeout(() => { if (S.source === source) connect(); }, 1000);
}

function onEvent(block) {
  let name = "message", data = "";
  for (const line of block.split("\n")) {
    if (line.startsWith("event: ")) name = line.slice(7);
    else if (line.startsWith("data: ")) data += line.slice(6);
  }
  if (name === "fleet") onFleet(JSON.parse(data));
  else if (name === "device") onDetail(JSON.parse(data));
  else if (name === "closed") $("conn").title = JSON.parse(data).reason || "";  // the server's reason; we reconnect
}

function authHeaders() {
  return S.token ? {"Authorization": `Bearer ${S.token}`} : {};
}

function setConn(live) {
  $("conn").classList.toggle("live", live);
  $("conn-text").textContent = live ? "live" : "reconnecting";
}

function onFleet(msg) {
  const now = performance.now();
  const st = S.stats;
  st.events += 1; st.rowsApplied += msg.rows.length; st.lastEventMs = Date.now();
  st.window.push([now, msg.rows.length]);
  while (st.window.length && now - st.window[0][0] > 5000) st.window.shift();
  const span = st.window.length > 1 ? (now - st.window[0][0]) / 1000 : 0;
  st.eventsPerSec = span ? (st.window.length - 1) / span : 0;
  st.rowsPerSec = span ? st.window.slice(1).reduce((a, w) => a + w[1], 0) / span : 0;
  const sent = msg.full ? new Set(msg.rows.map((r) => r.device)) : null;
  const gone = sent ? [...S.rows.keys()].filter((d) => !sent.has(d)) : (msg.gone || []);
  for (const device of gone) {         // forgotten by the dashboard (silent for long, or past its row limit)
    S.rows.delete(device); S.trs.delete(device); S.orderAt = 0;
  }
  for (const row of msg.rows) {
    const known = S.rows.has(row.device);
    S.rows.set(row.device, row);
    if (!known) S.orderAt = 0;
  }
  showSummary(msg.summary);
  if (S.device && S.rows.has(S.device)) showLive(S.rows.get(S.device));
  if (!S.dirty) { S.dirty = true; requestAnimationFrame(renderFleet); }
}

function showSummary(sum) {
  if (!sum) return;
  const rate = S.stats.rowsPerSec;
  $("summary").innerHTML = `<b>${sum.devices}</b> devices &middot; <b>${sum.alive}</b> alive &middot; ` +
    `<b>${sum.calibrated}</b> calibrated &middot; <span id="alert-count" class="${sum.alerts ? "alerting" : ""}" ` +
    `data-count="${sum.alerts || 0}"><b>${sum.alerts || 0}</b> alert${sum.alerts === 1 ? "" : "s"}</span> ` +
    `&middot; ${rate.toFixed(0)} row updates/s`;
}

// ------------------------------------------------------------------------------------------------ fleet table
const COLUMNS = ["alive", "device", "sensor", "state", "method", "residual_ut", "coverage", "calibrated_ms",
  "true_heading_deg", "pitch_deg", "roll_deg", "field_ut", "alerts"];

function ageText(ms) {
  if (ms == null) return "\u2013";
  const s = Math.max(0, (Date.now() - ms) / 1000);
  if (s < 90) return `${s.toFixed(0)} s`;
  if (s < 5400) return `${(s / 60).toFixed(0)} min`;
  if (s < 172800) return `${(s / 3600).toFixed(1)} h`;
  return `${(s / 86400).toFixed(0)} d`;
}

const DRIFT_CAUSE = {field_strength: "field strength", dip: "dip angle", calibration_age: "calibration age"};

function driftCause(a) {
  const unit = a.unit === "uT" ? "\u00b5T" : a.unit;
  return `${DRIFT_CAUSE[a.kind] || a.kind}: ${fmt(a.measured, 1)} ${unit} against ${fmt(a.expected, 1)} ${unit}`;
}

function alertBadges(row, withAdvice) {
  const fused = row.fused ? '<span class="badge session" title="attitude from the gyroscope-aided filter">fused</span>' : "";
  const drift = (row.drift || []).map((a) => `<div class="drift" data-kind="${esc(a.kind)}" data-since="${a.since_ms}"><span class="badge alert" ` +
    `title="${esc(driftCause(a))}">drift: ${esc(DRIFT_CAUSE[a.kind] || a.kind)}</span>` +
    (withAdvice ? `<span class="advice">${esc(a.advice)}</span>` : "") + "</div>").join("");
  const others = row.alerts.filter((a) => !a.startsWith("drift: "));
  return drift + fused + (others.map((a) => `<span class="badge alert">${esc(a)}</span>`).join("") ||
    (drift ? "" : '<span class="badge note">ok</span>'));
}

function stateBadge(row) {
  const status = row.status || (row.session ? "session" : row.state);
  const text = status === "drifted" ? "calibrated \u00b7 drift alert" : status;
  return `<span class="badge ${esc(status === "drifted" ? "alert" : status)}" data-status="${esc(status)}">${esc(text)}</span>`;
}

function makeRow(device) {
  const tr = document.createElement("tr");
  tr.dataset.device = device;
  const cells = {};
  for (const key of COLUMNS) {
    const td = document.createElement("td");
    td.dataset.key = key;
    if (["residual_ut", "calibrated_ms", "true_heading_deg", "pitch_deg", "roll_deg", "field_ut"].includes(key)) {
      td.className = "num";
    }
    tr.appendChild(td);
    cells[key] = {td, text: null};
  }
  tr.addEventListener("click", () => { location.hash = `#/device/${encodeURIComponent(device)}`; });
  return {tr, cells};
}

function setCell(cell, html) {
  if (cell.text !== html) { cell.td.innerHTML = html; cell.text = html; }
}

function fillRow(entry, row) {
  const c = entry.cells;
  const alive = row.alive === true ? "on" : row.alive === false ? "off" : "";
  setCell(c.alive, `<span class="alive ${alive}" title="${row.alive === true ? "alive" : row.alive === false ?
    "token gone" : "no token seen"}"></span>`);
  setCell(c.device, esc(row.device));
  setCell(c.sensor, esc(row.sensor) || "\u2013");
  setCell(c.state, stateBadge(row));
  setCell(c.method, esc(row.method) || "\u2013");
  setCell(c.residual_ut, fmt(row.residual_ut, 2));
  const cov = row.coverage == null ? 0 : row.coverage;
  setCell(c.coverage, `<span class="cov"><span class="track"><span class="fill" style="width:${(cov * 100).toFixed(0)}%">` +
    `</span></span>${row.coverage == null ? "\u2013" : (cov * 100).toFixed(0) + " %"}</span>`);
  setCell(c.calibrated_ms, ageText(row.calibrated_ms));
  const h = row.true_heading_deg;
  setCell(c.true_heading_deg, h == null ? "\u2013" :
    `<span class="arrow" style="transform:rotate(${h.toFixed(0)}deg)">\u2191</span>${fmt(h, 1)}\u00b0`);
  c.true_heading_deg.td.dataset.seq = row.seq == null ? "" : String(row.seq);
  c.true_heading_deg.td.dataset.heading = h == null ? "" : String(h);
  c.true_heading_deg.td.title = `magnetic ${deg(row.heading_deg)}`;
  setCell(c.pitch_deg, deg(row.pitch_deg));
  setCell(c.roll_deg, deg(row.roll_deg));
  setCell(c.field_ut, fmt(row.field_ut, 1));
  setCell(c.alerts, alertBadges(row, true));
}

function sortValue(row, key) {
  const v = key === "alerts" ? row.alerts.length : row[key];
  return v == null ? -Infinity : v;
}

function computeOrder() {
  const f = S.filter;
  const list = [];
  for (const row of S.rows.values()) {
    if (f) {
      const hay = `${row.device} ${row.sensor} ${row.status || row.state} ${row.method || ""} ${row.alerts.join(" ")}`.toLowerCase();
      if (!hay.includes(f)) continue;
    }
    list.push(row);
  }
  const key = S.sortKey, sign = S.sortDesc ? -1 : 1;
  list.sort((a, b) => {
    const x = sortValue(a, key), y = sortValue(b, key);
    if (x < y) return -sign;
    if (x > y) return sign;
    return a.device < b.device ? -1 : a.device > b.device ? 1 : 0;
  });
  return list.map((r) => r.device);
}

function renderFleet() {
  S.dirty = false;
  if ($("fleet-view").classList.contains("hidden")) return;
  const t0 = performance.now();
  const body = $("fleet-body");
  if (!S.orderAt || t0 - S.orderAt > 1000) {       // re-sort at most once a second: rows do not jump about
    const order = computeOrder();
    const same = order.length === S.order.length && order.every((d, i) => d === S.order[i]);
    if (!same) {
      const frag = document.createDocumentFragment();
      for (const device of order) {
        let entry = S.trs.get(device);
        if (!entry) { entry = makeRow(device); S.trs.set(device, entry); fillRow(entry, S.rows.get(device)); }
        frag.appendChild(entry.tr);
      }
      body.replaceChildren(frag);
      S.order = order;
    }
    S.orderAt = t0;
  }
  const [first, last] = visibleRange(body);  // only rows on screen are redrawn: 1,000 devices stay smooth
  for (let i = first; i < last; i++) fillRow(S.trs.get(S.order[i]), S.rows.get(S.order[i]));
  $("shown").textContent = `${S.order.length} of ${S.rows.size} shown`;
  $("fleet-empty").classList.toggle("hidden", S.rows.size > 0);
  S.stats.renders += 1;
  S.stats.renderMs = performance.now() - t0;
}

function visibleRange(body) {
  const n = S.order.length;
  if (!n) return [0, 0];
  const firstRow = body.rows[0];
  const height = firstRow ? Math.max(firstRow.offsetHeight, 1) : 30;
  const top = body.getBoundingClientRect().top;
  const from = Math.floor(Math.max(0, -top) / height) - 5;
  const to = Math.ceil((Math.max(0, -top) + window.innerHeight) / height) + 5;
  return [Math.max(0, from), Math.min(n, to)];
}

function setupTable() {
  window.addEventListener("scroll", () => {
    if (!S.dirty) { S.dirty = true; requestAnimationFrame(renderFleet); }
  }, {passive: true});
  for (const th of document.querySelectorAll("#fleet th")) {
    th.addEventListener("click", () => {
      const key = th.dataset.key;
      if (S.sortKey === key) S.sortDesc = !S.sortDesc; else { S.sortKey = key; S.sortDesc = false; }
      for (const other of document.querySelectorAll("#fleet th")) other.classList.remove("sorted", "desc");
      th.classList.add("sorted");
      th.classList.toggle("desc", S.sortDesc);
      S.orderAt = 0; renderFleet();
    });
  }
  document.querySelector('#fleet th[data-key="device"]').classList.add("sorted");
  $("filter").addEventListener("input", () => {
    S.filter = $("filter").value.trim().toLowerCase(); S.orderAt = 0; renderFleet();
  });
}

// ------------------------------------------------------------------------------------------------ routing
function route() {
  const m = location.hash.match(/^#\/device\/(.+)$/);
  const device = m ? decodeURIComponent(m[1]) : null;
  $("fleet-view").classList.toggle("hidden", !!device);
  $("device-view").classList.toggle("hidden", !device);
  $("nav-fleet").classList.toggle("active", !device);
  $("nav-device").classList.toggle("hidden", !device);
  $("nav-device").classList.toggle("active", !!device);
  if (device) $("nav-device").textContent = device;
  if (device !== S.device) {
    S.device = device; S.detail = null; S.sphereKey = null;
    if (device) enterDevice(device);
    connect();
  }
  if (!device) { S.orderAt = 0; renderFleet(); }
}

// ------------------------------------------------------------------------------------------------ device view
let dial = null, horizon = null;

function enterDevice(device) {
  $("dev-name").textContent = device;
  $("c-message").textContent = "";
  for (const id of ["cloud", "sphere", "heading-plot"]) if (window.Plotly) Plotly.purge($(id));
  S.history = null; showInForce(null, -1, []);
  S.rowCalibration = S.rows.has(device) ? S.rows.get(device).calibration_id : null;
  loadHistory(device);
  if (S.rows.has(device)) showLive(S.rows.get(device));
}

function showLive(row) {
  if (!dial) { dial = buildDial($("dial")); horizon = buildHorizon($("horizon")); }
  dial.set(row.true_heading_deg, row.heading_deg, row.heading_sigma_deg);
  horizon.set(row.pitch_deg, row.roll_deg);
  $("v-true").textContent = deg(row.true_heading_deg) +
    (row.heading_sigma_deg == null ? "" : ` \u00b1 ${deg(row.heading_sigma_deg)}`);
  $("v-mag").textContent = deg(row.heading_deg);
  $("v-decl").textContent = deg(row.declination_deg, 2);
  $("v-pitch").textContent = deg(row.pitch_deg);
  $("v-roll").textContent = deg(row.roll_deg);
  $("quat-box").classList.toggle("hidden", !row.quat_wxyz);
  if (row.quat_wxyz) $("v-quat").textContent = row.quat_wxyz.map((q) => q.toFixed(3)).join(", ");
  $("v-field").textContent = row.field_ut == null ? "\u2013" : `${fmt(row.field_ut, 1)} \u00b5T`;
  $("v-dip").textContent = deg(row.dip_deg);
  $("v-alerts").innerHTML = alertBadges(row, false);
  showDrift(row);
  $("v-truth").textContent = row.truth_error_deg == null ? "" :
    `error against the simulator's truth: ${fmt(row.truth_error_deg, 2)}\u00b0`;
  $("dev-badges").innerHTML = stateBadge(row) +
    `<span class="badge note">${esc(row.sensor) || "sensor ?"}</span>` +
    `<span class="badge note">${row.alive === false ? "offline" : row.alive ? "alive" : "no token"}</span>`;
  showGauges(row, S.detail && S.detail.earth);
  showControl(row);
  sphereNote(row);
  if (row.calibration_id !== S.rowCalibration) {  // another calibration came into force: its history again
    S.rowCalibration = row.calibration_id;
    if (row.calibration_id && row.calibration_id !== S.historyFor) loadHistory(S.device, row.calibration_id);
  }
}

function showDrift(row) {
  const list = row.drift || [];
  $("dev-drift").classList.toggle("hidden", !list.length);
  const html = list.map((a) => `<li data-kind="${esc(a.kind)}" data-since="${a.since_ms}"><span class="when">${esc(new Date(a.since_ms).toLocaleString())}` +
    `</span> <b class="cause">${esc(driftCause(a))}</b><div class="advice">${esc(a.advice)}</div></li>`).join("");
  if ($("dev-drift-list").dataset.html !== html) { $("dev-drift-list").innerHTML = html; $("dev-drift-list").dataset.html = html; }
}

function showGauges(row, earth) {
  const place = (id, bandId, value, lo, hi, want, tol) => {
    const pos = (v) => `${Math.max(0, Math.min(100, (v - lo) / (hi - lo) * 100))}%`;
    if (value != null) $(id).style.left = pos(value);
    if (want != null) {
      $(bandId).style.left = pos(want - tol);
      $(bandId).style.width = `calc(${pos(want + tol)} - ${pos(want - tol)})`;
    }
  };
  const total = earth ? earth.total_ut : null, incl = earth ? earth.inclination_deg : null;
  $("v-field-wmm").textContent = total == null ? "(no --location: no WMM)" : `WMM ${fmt(total, 1)} \u00b5T \u00b115 %`;
  $("v-dip-wmm").textContent = incl == null ? "" : `WMM ${fmt(incl, 1)}\u00b0 \u00b15\u00b0`;
  place("g-field", "g-field-band", row.field_ut, 0, 100, total, total ? total * 0.15 : 0);
  place("g-dip", "g-dip-band", row.dip_deg, -90, 90, incl, 5);
}

function showControl(row) {
  const cov = row.coverage;
  const ready = row.session && row.accepted === true;
  $("c-state").className = `badge ${row.state}`;
  $("c-state").textContent = row.session ? "session" : row.state;
  $("c-method").textContent = row.method || "";
  $("c-samples").textContent = row.samples ? `${row.samples} samples` : "";
  $("c-bar").style.width = `${((cov || 0) * 100).toFixed(0)}%`;
  $("c-pct").textContent = cov == null ? "\u2013" : `coverage ${(cov * 100).toFixed(0)} %`;
  $("c-bar").parentElement.classList.toggle("ready", ready || row.state === "calibrated");
  let next;
  if (ready) next = "The fit passes the gate: commit it (or keep turning to improve it).";
  else if (row.state === "session" || row.state === "collecting") {
    next = row.missing.length ? `Next: ${row.missing.join("; ")}` : "Keep turning the device through every attitude.";
  } else if (row.state === "calibrated") next = "Calibrated. Start a session to calibrate again.";
  else next = "Waiting for samples.";
  $("c-next").textContent = next;
  $("c-next").classList.toggle("ready", ready);
  $("c-reason").textContent = row.reason || "";
  $("b-commit").disabled = !ready;
  $("b-commit").title = ready ? "store this calibration and put it in force" : "enabled once the fit passes the gate";
  $("b-abort").disabled = !row.session;
  $("b-commit").classList.toggle("ready", ready);
}

function onDetail(detail) {
  if (!detail || detail.unknown || !S.device || detail.row.device !== S.device) return;
  S.detail = detail;
  showLive(detail.row);
  if (!window.Plotly || document.hidden) return;
  const t0 = performance.now();
  if (t0 - S.plotAt < Math.max(900, 4 * S.plotCost)) return;  // plots take at most a quarter of the page's time
  drawCloud(detail);
  const key = detail.cells.join("") + (detail.row.missing || []).join();
  if (key !== S.sphereKey) { S.sphereKey = key; drawSphere(detail); }
  drawHeadings(detail);
  S.plotAt = performance.now();
  S.plotCost = S.plotAt - t0;
  S.stats.plotMs = S.plotCost;
  S.stats.details = (S.stats.details || 0) + 1;
}

// legends sit at the top left, the toolbar (cloud only, on hover) at the top right: they never overlap
const PLOT_LAYOUT = {paper_bgcolor: "rgba(0,0,0,0)", plot_bgcolor: "rgba(0,0,0,0)", font: {color: "#dbe3ea", size: 11},
  margin: {l: 40, r: 10, t: 30, b: 35}, showlegend: true,
  legend: {orientation: "h", x: 0, xanchor: "left", y: 1.0, yanchor: "bottom", itemsizing: "constant"}};
const PLOT_CONFIG = {displaylogo: false, responsive: true, displayModeBar: "hover", modeBarButtonsToRemove: ["toImage"]};
const STILL_CONFIG = {displaylogo: false, responsive: true, displayModeBar: false};
const col = (pts, i) => pts.map((p) => p[i]);

function drawCloud(d) {
  const raw = d.raw, cal = d.calibrated;
  $("cloud-note").textContent = raw.length ? `${raw.length} raw, ${cal.length} calibrated points (\u00b5T)` :
    "collecting points\u2026";
  let traces, layout;
  if (S.cloudMode === "3d") {
    const t3 = (pts, name, color) => ({type: "scatter3d", mode: "markers", name, x: col(pts, 0), y: col(pts, 1),
      z: col(pts, 2), marker: {size: 2, color, opacity: 0.8}});
    traces = [t3(raw, "raw", "#ff7a59"), t3(cal, "calibrated", "#4fa3ff")];
    const axis = (t) => ({title: {text: t}, gridcolor: "#2a3542", zerolinecolor: "#5d6b79", backgroundcolor: "rgba(0,0,0,0)"});
    layout = {...PLOT_LAYOUT, margin: {l: 0, r: 0, t: 0, b: 0},
      scene: {aspectmode: "data", xaxis: axis("x"), yaxis: axis("y"), zaxis: axis("z"),
        camera: {eye: {x: 1.5, y: 1.5, z: 1.0}}}, uirevision: "cloud3d"};
  } else {
    traces = [];
    const pairs = [[0, 1, "x", "y"], [0, 2, "x", "z"], [1, 2, "y", "z"]];
    pairs.forEach(([i, j], k) => {
      const ax = k ? String(k + 1) : "";
      traces.push({type: "scatter", mode: "markers", name: "raw", legendgroup: "raw", showlegend: k === 0,
        x: col(raw, i), y: col(raw, j), xaxis: `x${ax}`, yaxis: `y${ax}`, marker: {size: 3, color: "#ff7a59"}});
      traces.push({type: "scatter", mode: "markers", name: "calibrated", legendgroup: "cal", showlegend: k === 0,
        x: col(cal, i), y: col(cal, j), xaxis: `x${ax}`, yaxis: `y${ax}`, marker: {size: 3, color: "#4fa3ff"}});
    });
    const ax = (t, anchor, domain) => ({title: {text: t}, gridcolor: "#2a3542", zerolinecolor: "#5d6b79", anchor, domain});
    layout = {...PLOT_LAYOUT, uirevision: "cloudproj",
      xaxis: ax("x", "y", [0, 0.3]), yaxis: {...ax("y", "x"), scaleanchor: "x"},
      xaxis2: ax("x", "y2", [0.35, 0.65]), yaxis2: {...ax("z", "x2"), scaleanchor: "x2"},
      xaxis3: ax("y", "y3", [0.7, 1]), yaxis3: {...ax("z", "x3"), scaleanchor: "x3"}};
  }
  Plotly.react($("cloud"), traces, layout, PLOT_CONFIG);
}

function cellCentres(n) {
  const out = [];
  for (let k = 0; k < n; k++) {
    const i = k + 0.5, z = 1 - 2 * i / n, phi = Math.PI * (3 - Math.sqrt(5)) * i, r = Math.sqrt(1 - z * z);
    out.push([r * Math.cos(phi), r * Math.sin(phi), z]);
  }
  return out;
}
const CELLS = cellCentres(100);

// The one coverage figure (the calibrator's), wherever it shows: fleet row, progress bar, this note.
function sphereNote(row) {
  const missing = row.missing && row.missing.length ? ` Missing: ${row.missing.join("; ")}.` : "";
  const text = (row.coverage != null ? `Coverage ${(row.coverage * 100).toFixed(0)} % ` +
    "(the calibrator's figure). " : "") + "Green: directions this page saw in the last raw samples." + missing;
  if ($("sphere-note").textContent !== text) $("sphere-note").textContent = text;
}

// The sphere of directions as an equal-area map: azimuth around the body z axis against z (Lambert cylindrical).
function drawSphere(d) {
  const hit = d.cells, row = d.row;
  const az = (p) => ((Math.atan2(p[1], p[0]) * 180 / Math.PI) + 360) % 360;
  const pick = (want) => CELLS.filter((_, k) => !!hit[k] === want);
  const trace = (pts, name, color, size) => ({type: "scatter", mode: "markers", name, x: pts.map(az),
    y: pts.map((p) => p[2]), marker: {size, color, line: {width: 0}},
    hovertemplate: "azimuth %{x:.0f}\u00b0, z %{y:.2f}<extra></extra>"});
  Plotly.react($("sphere"), [trace(pick(true), "covered", "#3fbf7f", 13), trace(pick(false), "missing", "#f0605a", 9)],
    {...PLOT_LAYOUT, uirevision: "sphere", margin: {l: 50, r: 10, t: 10, b: 40},
      xaxis: {range: [-10, 370], tickvals: [0, 90, 180, 270, 360], ticktext: ["+x", "+y", "\u2212x", "\u2212y", "+x"],
        gridcolor: "#2a3542", zeroline: false, title: {text: "direction around z"}},
      yaxis: {range: [-1.1, 1.1], tickvals: [-1, 0, 1], ticktext: ["\u2212z (up)", "0", "+z (down)"],
        gridcolor: "#2a3542", zeroline: false}}, STILL_CONFIG);
  sphereNote(row);
}

// 60 s of headings as lines: true solid, magnetic dashed; a wrap through north breaks the line instead of
// drawing a vertical stroke across the plot.
function headingLine(x, y) {
  const xs = [], ys = [];
  for (let i = 0; i < y.length; i++) {
    if (i && Math.abs(y[i] - y[i - 1]) > 180) { xs.push(null); ys.push(null); }
    xs.push(x[i]); ys.push(y[i]);
  }
  return [xs, ys];
}

function drawHeadings(d) {
  const h = d.headings;
  if (!h.length) return;
  const t0 = h[h.length - 1][0];
  const x = h.map((p) => (p[0] - t0) / 1000);
  const [xt, yt] = headingLine(x, h.map((p) => p[2]));
  const [xm, ym] = headingLine(x, h.map((p) => p[1]));
  Plotly.react($("heading-plot"), [
    {type: "scatter", mode: "lines", name: "true", x: xt, y: yt, line: {width: 2, color: "#4fa3ff"},
      connectgaps: false},
    {type: "scatter", mode: "lines", name: "magnetic", x: xm, y: ym, line: {width: 1.5, color: "#ff7a59", dash: "dash"},
      connectgaps: false},
  ], {...PLOT_LAYOUT, uirevision: "headings", xaxis: {title: {text: "seconds before now"}, range: [-60, 0],
    gridcolor: "#2a3542"}, yaxis: {range: [0, 360], dtick: 90, gridcolor: "#2a3542", title: {text: "deg"}}},
    STILL_CONFIG);
}

// ------------------------------------------------------------------------------------------------ control
async function control(action, extra) {
  const device = S.device;
  const msg = $("c-message");
  if (!S.token) {
    $("token-row").classList.remove("hidden");
    msg.className = "message small err";
    msg.textContent = "Enter the control token printed when the dashboard started.";
    return;
  }
  msg.className = "message small"; msg.textContent = `${action}\u2026`;
  const body = {action, ...(extra || {})};
  if (action === "start") body.method = $("c-method-select").value;
  try {
    const res = await fetch(`/api/devices/${encodeURIComponent(device)}/calibrate`, {method: "POST",
      headers: {"Content-Type": "application/json", "Authorization": `Bearer ${S.token}`}, body: JSON.stringify(body)});
    const data = await res.json();
    const ok = res.ok && data.ok !== false;
    msg.className = `message small ${ok ? "ok" : "err"}`;
    msg.textContent = data.message || data.error || `HTTP ${res.status}`;
    if (res.status === 401) $("token-row").classList.remove("hidden");
    if (ok && data.progress) showControl({...S.rows.get(device), ...progressRow(data)});
    if (ok && (action === "commit" || action === "rollback")) {
      loadHistory(device, data.calibration && data.calibration.id);
    }
  } catch (err) {
    msg.className = "message small err"; msg.textContent = String(err);
  }
}

function progressRow(reply) {
  const p = reply.progress || {};
  return {state: p.state || reply.state, session: !!p.session, method: p.method, samples: p.samples,
    coverage: p.coverage, missing: p.missing || [], reason: p.reason || "", accepted: p.accepted};
}

async function loadHistory(device, inForceId) {
  const body = $("history-body");
  body.innerHTML = '<tr><td colspan="10" class="muted">asking the calibrator\u2026</td></tr>';
  const row = S.rows.get(device);
  S.historyLoading = true;
  S.historyFor = inForceId || (row ? row.calibration_id : null);
  try {
    const res = await fetch(`/api/devices/${encodeURIComponent(device)}/history?limit=10`, {headers: authHeaders()});
    const data = await res.json();
    if (device !== S.device) return;
    if (!res.ok) { body.innerHTML = `<tr><td colspan="10" class="muted">${esc(data.error)}</td></tr>`; return; }
    const current = S.historyFor;
    const inForce = data.records.find((r) => r.id === current) || data.records.find((r) => r.accepted) || null;
    S.history = {...data, inForce};
    showInForce(inForce, data.records.indexOf(inForce), data.changes || []);
    body.innerHTML = data.records.map((r, i) => historyRow(r, (data.changes || [])[i], r === inForce,
      !!inForce && r.id === inForce.id)).join("") ||
      '<tr><td colspan="10" class="muted">no stored calibration yet</td></tr>';
  } catch (err) {
    body.innerHTML = `<tr><td colspan="10" class="muted">${esc(err)}</td></tr>`;
  } finally {
    S.historyLoading = false;
  }
}

function changeText(change) {
  if (!change) return "\u2013";
  return `${esc(change.action || "")}${change.by ? ` by ${esc(change.by)}` : ""}`;
}

function historyRow(r, change, inForce, sameAsInForce) {
  const q = r.quality || {};
  const when = r.created_ns ? new Date(r.created_ns / 1e6).toLocaleString() : "\u2013";
  const res = q.residual_rms_ut != null ? `${fmt(q.residual_rms_ut, 2)} \u00b5T (${fmt(q.residual_rms_pct, 2)} %)` : "\u2013";
  const held = q.holdout_rms_ut != null ? `${fmt(q.holdout_rms_ut, 2)} \u00b5T` : "\u2013";
  const cov = q.coverage != null ? `${(q.coverage * 100).toFixed(0)} %` : "\u2013";
  const ratio = q.radius_ratio != null ? fmt(q.radius_ratio, 3) : "\u2013";
  const gate = `<span class="badge ${r.accepted ? "calibrated" : "alert"}">${r.accepted ? "accepted" : "rejected"}</span>` +
    `<span class="muted small">${esc(r.reason)}</span>`;
  const act = inForce ? '<span class="badge calibrated">in force</span>' : r.accepted && !sameAsInForce ?
    `<button class="rollback" data-id="${esc(r.id)}" title="put this calibration back in force (needs the token)">` +
    "Roll back to this</button>" : "";
  return `<tr data-id="${esc(r.id)}"><td>${when}</td><td><code>${esc(r.id)}</code></td><td>${esc(r.method)}</td>` +
    `<td class="num">${res}</td><td class="num">${held}</td><td class="num">${cov}</td><td class="num">${ratio}</td>` +
    `<td>${gate}</td><td class="small">${changeText(change)}</td><td>${act}</td></tr>`;
}

function showInForce(record, index, changes) {
  $("b-export").disabled = !record;
  if (!record) {
    $("f-id").textContent = "none"; $("f-offset").textContent = "\u2013"; $("f-matrix").innerHTML = "";
    $("f-strength").textContent = "\u2013"; $("f-made").textContent = "\u2013";
    return;
  }
  const unit = (u) => (u === "ut" ? "\u00b5T" : u || "");
  $("f-id").textContent = record.id;
  $("f-offset").textContent = `[${(record.offset || []).map((v) => fmt(v, 2)).join(", ")}] ${unit(record.unit)}`;
  $("f-matrix").innerHTML = (record.matrix || []).map((r) =>
    `<tr>${r.map((v) => `<td>${fmt(v, 4)}</td>`).join("")}</tr>`).join("");
  $("f-strength").textContent = record.field_strength ? `${fmt(record.field_strength, 2)} ${unit(record.output_unit)}` : "\u2013";
  const change = changes[index];
  $("f-made").innerHTML = `${record.created_ns ? esc(new Date(record.created_ns / 1e6).toLocaleString()) : "\u2013"}` +
    ` &middot; ${esc(record.method)} &middot; ${changeText(change)}`;
}

function exportCalibration() {
  const record = S.history && S.history.inForce;
  if (!record) return;
  const blob = new Blob([JSON.stringify(record, null, 2) + "\n"], {type: "application/json"});
  const link = document.createElement("a");
  link.href = URL.createObjectURL(blob);
  link.download = `${S.device}-${record.id}.json`;
  document.body.appendChild(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(link.href), 1000);
}

// ------------------------------------------------------------------------------------------------ start
function start() {
  takeToken();
  setupTable();
  for (const [id, action] of [["b-start", "start"], ["b-commit", "commit"], ["b-abort", "abort"]]) {
    $(id).addEventListener("click", () => control(action));
  }
  $("b-export").addEventListener("click", exportCalibration);
  $("history-body").addEventListener("click", (e) => {
    const button = e.target.closest("button.rollback");
    if (button) control("rollback", {to: button.dataset.id});
  });
  for (const tab of document.querySelectorAll(".tab")) {
    tab.addEventListener("click", () => {
      S.cloudMode = tab.dataset.cloud;
      for (const t of document.querySelectorAll(".tab")) t.classList.toggle("active", t === tab);
      if (window.Plotly) Plotly.purge($("cloud"));
      if (S.detail) drawCloud(S.detail);
    });
  }
  window.addEventListener("hashchange", route);
  route();
  if (!S.source) connect();
  setInterval(() => { if (!S.dirty && S.rows.size) { S.dirty = true; requestAnimationFrame(renderFleet); } }, 1000);
}

document.addEventListener("DOMContentLoaded", start);
