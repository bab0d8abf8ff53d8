// RMS error against wall time as an inline SVG: linear time, log10 error.
"use strict";

const SUPER = { "-": "⁻", 0: "⁰", 1: "¹", 2: "²", 3: "³", 4: "⁴", 5: "⁵", 6: "⁶", 7: "⁷", 8: "⁸", 9: "⁹" };
const pow10 = k => "10" + String(k).split("").map(c => SUPER[c]).join("");

function niceStep(span, n) {
  const raw = span / n, mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const f = raw / mag;
  return (f < 1.5 ? 1 : f < 3.5 ? 2 : f < 7.5 ? 5 : 10) * mag;
}

// series: [{cls: "estimate"|"measured", points: [[t, rms, barrier], ...]}]
function drawChart(svg, series) {
  const W = 640, H = 300, m = { l: 58, r: 14, t: 12, b: 40 };
  svg.replaceChildren();
  for (const s of series) svg.dataset[s.cls + "Points"] = s.points.length;
  const pts = series.flatMap(s => s.points).filter(p => p[1] > 0 && isFinite(p[1]));
  if (!pts.length) {
    svg.append(el("text", { x: W / 2, y: H / 2, "text-anchor": "middle", text: "waiting for the first barrier…" }));
    return;
  }
  const tmax = Math.max(...pts.map(p => p[0]), 1e-3);
  let lo = Math.floor(Math.log10(Math.min(...pts.map(p => p[1]))));
  let hi = Math.ceil(Math.log10(Math.max(...pts.map(p => p[1]))));
  if (hi <= lo) hi = lo + 1;
  const x = t => m.l + (t / tmax) * (W - m.l - m.r);
  const y = v => m.t + ((hi - Math.log10(v)) / (hi - lo)) * (H - m.t - m.b);
  const every = Math.ceil((hi - lo) / 8);
  for (let k = lo; k <= hi; k++) {
    if ((k - lo) % every) continue;
    svg.append(el("line", { class: "grid", x1: m.l, x2: W - m.r, y1: y(10 ** k), y2: y(10 ** k) }),
      el("text", { x: m.l - 6, y: y(10 ** k) + 4, "text-anchor": "end", text: pow10(k) }));
  }
  const step = niceStep(tmax, 6);
  for (let t = 0; t <= tmax * 1.0001; t += step) {
    svg.append(el("line", { class: "grid", x1: x(t), x2: x(t), y1: m.t, y2: H - m.b }),
      el("text", { x: x(t), y: H - m.b + 15, "text-anchor": "middle", text: +t.toPrecision(6) }));
  }
  svg.append(el("line", { class: "axis", x1: m.l, x2: m.l, y1: m.t, y2: H - m.b }),
    el("line", { class: "axis", x1: m.l, x2: W - m.r, y1: H - m.b, y2: H - m.b }),
    el("text", { x: (m.l + W - m.r) / 2, y: H - 6, "text-anchor": "middle", text: "wall time since the job started (s)" }),
    el("text", { x: 12, y: (m.t + H - m.b) / 2, "text-anchor": "middle",
                 transform: `rotate(-90 12 ${(m.t + H - m.b) / 2})`, text: "RMS error (W/m²)" }));
  for (const s of series) {
    const p = s.points.filter(q => q[1] > 0 && isFinite(q[1]));
    if (!p.length) continue;
    const g = el("g", { "data-series": s.cls });
    g.append(el("polyline", { class: s.cls, points: p.map(q => x(q[0]).toFixed(1) + "," + y(q[1]).toFixed(1)).join(" ") }));
    if (p.length <= 300) {
      for (const q of p) {
        g.append(el("circle", { class: s.cls, cx: x(q[0]).toFixed(1), cy: y(q[1]).toFixed(1), r: 2.4 },
          el("title", { text: `barrier ${q[2]}: ${fmtSci(q[1], 3)} W/m² at ${q[0].toFixed(2)} s` })));
      }
    }
    svg.append(g);
  }
}
