// dcrad status pages: small helpers shared by the pages (no build step, no library)
"use strict";

const TERMINAL = new Set(["done", "failed", "cancelled"]);

function el(tag, attrs = {}, ...children) {
  const svg = ["svg", "line", "polyline", "circle", "text", "g", "rect", "title"].includes(tag);
  const e = svg ? document.createElementNS("http://www.w3.org/2000/svg", tag) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.setAttribute("class", v);
    else if (k === "text") e.textContent = v;
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

function fmtTime(s) {
  if (s == null || !isFinite(s)) return "–";
  s = Math.max(0, s);
  if (s < 60) return s.toFixed(1) + " s";
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = Math.floor(s % 60);
  return (h ? h + ":" + String(m).padStart(2, "0") : m) + ":" + String(sec).padStart(2, "0");
}

function fmtSci(v, digits = 2) {
  if (v == null || !isFinite(v)) return "–";
  if (v === 0) return "0";
  const a = Math.abs(v);
  return a >= 0.01 && a < 1e5 ? v.toPrecision(digits + 1) : v.toExponential(digits);
}

function fmtInt(v) {
  return v == null ? "–" : Number(v).toLocaleString("en-US");
}

function fmtBytes(b) {
  if (b == null) return "–";
  const u = ["B", "kB", "MB", "GB", "TB"];
  let i = 0;
  while (b >= 1000 && i < u.length - 1) { b /= 1000; i++; }
  return (i ? b.toFixed(1) : String(b)) + " " + u[i];
}

function stateBadge(node, state) {
  node.textContent = state;
  node.className = "state " + state;
}

async function getJSON(url) {
  const r = await fetch(url, { cache: "no-store" });
  const body = await r.json().catch(() => ({}));
  if (!r.ok) throw new Error(body.error || r.status + " " + r.statusText);
  return body;
}
