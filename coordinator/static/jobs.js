// The jobs page: polls /api/jobs and /api/workers every 2 s.
"use strict";

async function refresh() {
  const status = document.getElementById("status");
  try {
    const [{ jobs }, { workers }] = await Promise.all([getJSON("/api/jobs"), getJSON("/api/workers")]);
    const body = document.querySelector("#jobs tbody");
    body.replaceChildren(...(jobs.length ? jobs.map(j => {
      const badge = el("span");
      stateBadge(badge, j.state);
      return el("tr", { "data-job": j.id },
        el("td", {}, el("a", { href: j.url, text: j.id })),
        el("td", { class: "left" }, badge),
        el("td", { class: "left", text: j.scene }),
        el("td", { text: j.subscenes || "–" }),
        el("td", { class: "left", text: j.workers.join(", ") || "–" }),
        el("td", { text: fmtTime(j.elapsed_s) }),
        el("td", { text: j.barrier }),
        el("td", { text: fmtSci(j.residual) }));
    }) : [el("tr", {}, el("td", { colspan: 8, text: "no jobs yet: submit one with `dcrad submit`" }))]));
    document.querySelector("#workers tbody").replaceChildren(...workers.map(w => el("tr", {},
      el("td", { text: w.address }), el("td", { class: "left", text: w.name || "–" }),
      el("td", { class: "left", text: w.alive ? "alive" : "lost" }),
      el("td", { text: w.load }), el("td", { text: w.capacity }))));
    status.textContent = "updated " + new Date().toLocaleTimeString();
  } catch (e) {
    status.textContent = "coordinator unreachable: " + e.message;
  }
  setTimeout(refresh, 2000);
}

refresh();
