// magnet dashboard: the vehicles (issue 27, item 4; docs/vehicles.md). A row per vehicle above the fleet table and a
// view per vehicle (#/vehicle/ID): its compasses compared, the one that disagrees named with its cause and the fix.
// Asked of /api/vehicles (the compasses' @vehicle queryable) every VEHICLES_EVERY_MS while the fleet or a vehicle
// is shown. Uses app.js's S (token), $, esc, fmt and authHeaders.
"use strict";

const VEHICLES_EVERY_MS = 5000;
const V = {vehicles: [], vehicle: null, timer: null, busy: false, asked: 0, error: ""};
window.magnetVehicles = V;

// badge colours of style.css: calibrated (good), collecting (warning), alert (bad), note (muted)
const VERDICT_CLASS = {reference: "calibrated", agrees: "calibrated", "too-few-samples": "note", rotation: "alert",
  interference: "alert", calibration: "collecting"};

function verdictBadge(verdict) {
  return `<span class="badge ${VERDICT_CLASS[verdict] || "collecting"}">${esc(verdict)}</span>`;
}

function vehicleState(v) {
  if (!v.reference) return ["note", "comparing"];
  const wrong = (v.compasses || []).filter((c) => !["reference", "agrees", "too-few-samples"].includes(c.verdict));
  if (wrong.length) return ["alert", `${wrong.length} disagree${wrong.length > 1 ? "" : "s"}`];
  if (v.anomaly) return ["collecting", "local anomaly"];
  return ["calibrated", "agree"];
}

async function loadVehicles() {
  if (V.busy) return;
  V.busy = true;
  try {
    const res = await fetch("/api/vehicles", {headers: authHeaders()});
    const body = await res.json();
    if (!res.ok) throw new Error(body.error || res.statusText);
    V.vehicles = body.vehicles || [];
    V.error = (body.errors || []).join("; ");
  } catch (err) {
    V.error = String(err.message || err);
  } finally {
    V.busy = false;
    V.asked += 1;
  }
  renderVehicles();
  if (V.vehicle) renderVehicle();
}

function renderVehicles() {
  const body = $("vehicles-body");
  $("vehicles-box").classList.toggle("hidden", V.vehicles.length === 0);
  body.textContent = "";
  for (const v of V.vehicles) {
    const tr = document.createElement("tr");
    tr.dataset.vehicle = v.vehicle;
    const [cls, text] = vehicleState(v);
    const verdicts = (v.compasses || []).map((c) => `${esc(c.device)} ${verdictBadge(c.verdict)}`).join(" ");
    tr.innerHTML = `<td><span class="badge ${cls}">${esc(text)}</span> ${esc(v.vehicle)}</td>` +
      `<td class="num">${(v.compasses || []).length}</td><td>${esc(v.reference || "\u2013")}</td>` +
      `<td class="num">${fmt(v.field_ut)}</td><td class="num">${fmt(v.expected_ut)}</td>` +
      `<td>${verdicts}</td><td>${esc(v.summary)}</td>`;
    tr.addEventListener("click", () => { location.hash = `#/vehicle/${encodeURIComponent(v.vehicle)}`; });
    body.appendChild(tr);
  }
}

function parametersText(params) {
  return Object.entries(params || {}).map(([k, v]) => `${k}=${Number.isInteger(v) ? v : fmt(v, 2)}`).join(", ");
}

function renderVehicle() {
  const name = V.vehicle;
  const v = V.vehicles.find((x) => x.vehicle === name);
  $("veh-name").textContent = name;
  const body = $("vehicle-body");
  body.textContent = "";
  if (!v) {
    $("veh-badge").className = "badge note";
    $("veh-badge").textContent = V.asked ? "unknown" : "asking";
    $("veh-summary").textContent = V.asked ? `No compass compares vehicle ${name} now.` : "";
    $("veh-field").textContent = "";
    $("veh-note").textContent = V.error;
    return;
  }
  const [cls, text] = vehicleState(v);
  $("veh-badge").className = `badge ${cls}`;
  $("veh-badge").textContent = text;
  $("veh-summary").textContent = v.summary;
  $("veh-field").textContent = `|B| ${fmt(v.field_ut)} \u00b5T (reference ${v.reference || "\u2013"}), WMM ` +
    `${fmt(v.expected_ut)} \u00b5T${v.anomaly ? ": a local anomaly, not the vehicle's fault" : ""}`;
  for (const c of v.compasses || []) {
    const tr = document.createElement("tr");
    const named = c.named_rotation == null ? "\u2013" : `${c.named_rotation} (${fmt(c.named_distance_deg)}\u00b0 off)`;
    const motors = c.interference_pct == null ? "\u2013" : `${fmt(c.interference_pct)}`;
    tr.innerHTML = `<td><a href="#/device/${encodeURIComponent(c.device)}">${esc(c.device)}</a></td>` +
      `<td>${verdictBadge(c.verdict)}</td><td>${esc((c.causes || []).join(", "))}</td>` +
      `<td class="num">${fmt(c.angle_deg)}\u00b0</td><td class="num">${fmt(c.rotation_deg)}\u00b0</td>` +
      `<td>${esc(named)}</td><td class="num">${esc(motors)}</td><td class="num">${fmt(c.residual_ut, 2)}</td>` +
      `<td class="num">${c.samples}</td><td><code>${esc(parametersText(c.parameters))}</code></td>` +
      `<td>${esc(c.fix)}</td>`;
    body.appendChild(tr);
  }
  $("veh-note").textContent = V.error;
}

function routeVehicle() {
  const m = location.hash.match(/^#\/vehicle\/(.+)$/);
  V.vehicle = m ? decodeURIComponent(m[1]) : null;
  const device = /^#\/device\//.test(location.hash);
  $("vehicle-view").classList.toggle("hidden", !V.vehicle);
  $("nav-vehicle").classList.toggle("hidden", !V.vehicle);
  $("nav-vehicle").classList.toggle("active", !!V.vehicle);
  if (V.vehicle) {
    $("fleet-view").classList.add("hidden");
    $("nav-fleet").classList.remove("active");
    $("nav-vehicle").textContent = V.vehicle;
    renderVehicle();
  }
  clearInterval(V.timer);
  V.timer = null;
  if (!device) {  // the fleet or a vehicle is shown: keep the vehicles fresh
    loadVehicles();
    V.timer = setInterval(() => { if (!document.hidden) loadVehicles(); }, VEHICLES_EVERY_MS);
  }
}

// after app.js's start (registered first), so that its router has run before this one on every change
document.addEventListener("DOMContentLoaded", () => {
  window.addEventListener("hashchange", routeVehicle);
  routeVehicle();
});
