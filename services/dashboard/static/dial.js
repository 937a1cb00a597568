// Compass dial and attitude indicator, drawn once in SVG; updates only move transforms.
"use strict";

const SVG_NS = "http://www.w3.org/2000/svg";

function svgEl(tag, attrs, parent) {
  const el = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) el.setAttribute(k, v);
  if (parent) parent.appendChild(el);
  return el;
}

// A dial of radius 100 with a fixed card (north up) and two needles: true (blue) and magnetic (orange), and a
// wedge of +-sigma (the heading's uncertainty) about the true needle.
function buildDial(svg) {
  svg.innerHTML = "";
  svgEl("circle", {r: 104, fill: "#11181f", stroke: "#2a3542", "stroke-width": 2}, svg);
  for (let a = 0; a < 360; a += 5) {
    const long = a % 30 === 0, mid = a % 10 === 0;
    const r1 = long ? 84 : mid ? 90 : 94;
    const t = a * Math.PI / 180;
    svgEl("line", {x1: r1 * Math.sin(t), y1: -r1 * Math.cos(t), x2: 100 * Math.sin(t), y2: -100 * Math.cos(t),
      stroke: long ? "#dbe3ea" : "#5d6b79", "stroke-width": long ? 2 : 1}, svg);
  }
  const names = {0: "N", 90: "E", 180: "S", 270: "W"};
  for (let a = 0; a < 360; a += 30) {
    const t = a * Math.PI / 180, r = 72;
    const text = svgEl("text", {x: r * Math.sin(t), y: -r * Math.cos(t) + 5, "text-anchor": "middle",
      fill: a === 0 ? "#f0605a" : names[a] ? "#dbe3ea" : "#8595a5",
      "font-size": names[a] ? 16 : 10, "font-weight": names[a] ? 700 : 400}, svg);
    text.textContent = names[a] || String(a);
  }
  const needle = (color, width, length) => {
    const g = svgEl("g", {}, svg);
    svgEl("polygon", {points: `0,${-length} ${width},0 0,${length * 0.25} ${-width},0`, fill: color,
      opacity: 0.92}, g);
    return g;
  };
  // the true heading's one sigma: a wedge of +-sigma about the true needle (hidden when the compass sends none)
  const spread = svgEl("path", {fill: "#4fa3ff", opacity: 0.22, stroke: "#4fa3ff", "stroke-opacity": 0.5,
    "stroke-width": 1, visibility: "hidden"}, svg);
  const mag = needle("#ff7a59", 5, 62);
  const tru = needle("#4fa3ff", 7, 78);
  svgEl("circle", {r: 6, fill: "#dbe3ea"}, svg);
  return {
    set(trueDeg, magDeg, sigmaDeg) {
      if (trueDeg != null) tru.setAttribute("transform", `rotate(${trueDeg})`);
      if (magDeg != null) mag.setAttribute("transform", `rotate(${magDeg})`);
      const shown = trueDeg != null && sigmaDeg != null && sigmaDeg > 0;
      spread.setAttribute("visibility", shown ? "visible" : "hidden");
      if (!shown) return;
      const half = Math.min(sigmaDeg, 179.9) * Math.PI / 180, r = 98;
      const large = half > Math.PI / 2 ? 1 : 0;
      spread.setAttribute("d", `M 0 0 L ${-r * Math.sin(half)} ${-r * Math.cos(half)} ` +
        `A ${r} ${r} 0 ${large} 1 ${r * Math.sin(half)} ${-r * Math.cos(half)} Z`);
      spread.setAttribute("transform", `rotate(${trueDeg})`);
    },
  };
}

// An attitude indicator of radius 90: the horizon moves with pitch (1.6 px per degree) and turns with roll.
function buildHorizon(svg) {
  svg.innerHTML = "";
  const defs = svgEl("defs", {}, svg);
  const clip = svgEl("clipPath", {id: "hz-clip"}, defs);
  svgEl("circle", {r: 90}, clip);
  const body = svgEl("g", {"clip-path": "url(#hz-clip)"}, svg);
  const world = svgEl("g", {}, body);
  svgEl("rect", {x: -300, y: -600, width: 600, height: 600, fill: "#2f6aa3"}, world);
  svgEl("rect", {x: -300, y: 0, width: 600, height: 600, fill: "#7a5230"}, world);
  svgEl("line", {x1: -300, y1: 0, x2: 300, y2: 0, stroke: "#fff", "stroke-width": 2}, world);
  for (let p = -80; p <= 80; p += 10) {
    if (p === 0) continue;
    const y = -p * 1.6, w = p % 20 === 0 ? 30 : 15;
    svgEl("line", {x1: -w, y1: y, x2: w, y2: y, stroke: "#fff", "stroke-width": 1, opacity: 0.8}, world);
    if (p % 20 === 0) {
      const t = svgEl("text", {x: w + 4, y: y + 3, fill: "#fff", "font-size": 8}, world);
      t.textContent = String(p);
    }
  }
  svgEl("circle", {r: 90, fill: "none", stroke: "#2a3542", "stroke-width": 3}, svg);
  svgEl("path", {d: "M -45 0 L -15 0 L -8 8 M 45 0 L 15 0 L 8 8", stroke: "#ffd34d", "stroke-width": 4,
    fill: "none", "stroke-linecap": "round"}, svg);
  svgEl("circle", {r: 3, fill: "#ffd34d"}, svg);
  return {
    set(pitchDeg, rollDeg) {
      if (pitchDeg == null || rollDeg == null) return;
      world.setAttribute("transform", `rotate(${-rollDeg}) translate(0 ${pitchDeg * 1.6})`);
    },
  };
}

window.buildDial = buildDial;
window.buildHorizon = buildHorizon;
