// The job page: polls /api/jobs/{id} every 0.7 s until the job has ended.
"use strict";

const jobId = decodeURIComponent(location.pathname.split("/")[2] || "");
const api = "/api/jobs/" + encodeURIComponent(jobId);
const $ = id => document.getElementById(id);
const LEDGER = [["emitted", "emitted"], ["absorbed", "absorbed"], ["unshot", "unshot"], ["in_flight", "in flight (twins)"],
  ["escaped", "escaped"], ["back_faces", "back faces"]];
let cancelling = false;

function facts(j) {
  const p = j.progress;
  document.title = `dcrad: ${j.scene} (${j.state})`;
  $("job-id").textContent = j.id;
  $("scene").textContent = j.scene;
  stateBadge($("state"), j.state);
  $("elapsed").textContent = fmtTime(j.elapsed_s);
  $("residual").textContent = `${fmtSci(j.residual)} (${fmtSci(j.settings.tol)})`;
  $("rms").textContent = !p ? "–" : (p.error && p.error.rms_refl > 0
    ? `${(100 * p.error.rms_refl).toFixed(2)}% of reflected light` +
      (p.accuracy > 0 ? ` (target ${100 * p.accuracy}%)` : "") +
      ` · noise ${(100 * p.error.noise_refl).toFixed(2)}%, bias ${(100 * p.error.bias_refl).toFixed(2)}%` +
      ` · ${fmtSci(p.rms_estimate, 3)} W/m²`
    : fmtSci(p.rms_estimate, 3) + " W/m²");
  $("barrier").textContent = p ? p.barrier : 0;
  $("rays").textContent = p ? fmtInt(p.rays) : "–";
  $("shots").textContent = p ? fmtInt(p.shots) : "–";
  $("relayed").textContent = p ? fmtBytes(p.bytes_relayed) : "–";
  $("workers").textContent = j.workers.join(", ") || "–";
  $("error").hidden = !j.error;
  $("error").textContent = j.error;
  const running = !TERMINAL.has(j.state);
  $("cancel").hidden = $("cancel-note").hidden = !running;  // a button for running jobs only
  $("cancel").disabled = !running || cancelling;
  if (cancelling && running) $("cancel").textContent = "Cancelling…";
  $("links").replaceChildren(...(j.report_url ? [el("a", { href: j.report_url, text: "report (JSON)" }), " · "] : []),
    el("a", { href: api, text: "this job as JSON" }));
}

function chart(j) {
  const series = [{ cls: "estimate", ...j.curve.estimate }];
  if (j.curve.measured) series.push({ cls: "measured", ...j.curve.measured });
  drawChart($("chart"), series);
  $("legend").replaceChildren(...series.map(s => el("li", { class: s.cls },
    el("span", { class: "swatch " + s.cls }), el("span", { text: `${s.label} (${s.points.length} points)` }))));
}

function preview(j) {
  const img = $("preview");
  if (!j.preview || String(j.preview.version) === img.dataset.version) return;
  img.src = j.preview.url;
  img.hidden = false;  // no image element before the first preview (no broken-image icon)
  img.dataset.version = j.preview.version;
  $("preview-note").textContent = `barrier ${j.preview.barrier} (preview ${j.preview.version}); ` +
    (TERMINAL.has(j.state) ? "final state" : "refreshed at barriers, at most every few seconds");
}

function ledger(j) {
  const body = document.querySelector("#ledger tbody");
  if (!j.progress) return;
  const led = j.progress.ledger, emitted = led.total.emitted || 0;
  const row = ([key, label]) => {
    const tot = led.total[key], share = emitted > 0 ? (100 * tot / emitted).toFixed(2) + " %" : "–";
    return el("tr", { class: key === "emitted" ? "sum" : "" }, el("td", { text: label }),
      ...led[key].map(v => el("td", { text: fmtSci(v, 4) })), el("td", { text: fmtSci(tot, 4) }), el("td", { text: share }));
  };
  body.replaceChildren(...LEDGER.map(row));
  $("ledger-note").textContent = `emitted = absorbed + unshot + in flight + escaped + back faces; ` +
    `closure ${fmtSci(led.closure)}, residual (unshot + in flight) / emitted ${fmtSci(led.residual)}`;
}

function subscenes(j) {
  const subs = j.progress ? j.progress.subscenes : [];
  document.querySelector("#subscenes tbody").replaceChildren(...subs.map(s => el("tr", {},
    el("td", { text: s.cell }), el("td", { class: "left", text: s.worker || "–" }), el("td", { text: fmtInt(s.shots) }),
    el("td", { text: fmtInt(s.rays) }), el("td", { text: fmtSci(s.residual) }), el("td", { text: fmtBytes(s.twin_bytes) }),
    el("td", { text: s.reassigned }))));
}

async function poll() {
  let j;
  try {
    j = await getJSON(api);
  } catch (e) {
    $("error").hidden = false;
    $("error").textContent = "cannot reach the coordinator: " + e.message;
    setTimeout(poll, 2000);
    return;
  }
  facts(j); chart(j); preview(j); ledger(j); subscenes(j);
  // a finished job is final once its report (and the measured curve) is there
  if (!TERMINAL.has(j.state) || (j.state !== "failed" && !j.report_url)) setTimeout(poll, 700);
}

$("cancel").addEventListener("click", async () => {
  cancelling = true;
  $("cancel").disabled = true;
  $("cancel").textContent = "Cancelling…";
  try {
    const r = await fetch(api + "/cancel", { method: "POST" });
    if (!r.ok) throw new Error((await r.json().catch(() => ({}))).error || r.statusText);
  } catch (e) {
    cancelling = false;
    $("cancel").disabled = false;
    $("cancel").textContent = "Cancel job";
    $("error").hidden = false;
    $("error").textContent = "cancel failed: " + e.message;
  }
});

poll();
