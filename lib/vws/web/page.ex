defmodule Vws.Web.Page do
  @moduledoc """
  The dashboard: one HTML page with plain JavaScript that asks `/api/state` every 400 ms and
  redraws the workstations — partitions and their command statuses, device statuses, interlocks,
  link states and the recent WC dialogue — and, on a node of a cell, the cell: every workstation
  of every connected node with its state. Text from the equipment is only ever put into the page
  with `textContent`, never as HTML. The control form (a status query) appears only when the
  server has a control token, and sends the token the user types in the `x-vws-token` header.
  """

  @poll_ms 400

  @doc "The interval at which the page polls `/api/state`, in ms."
  @spec poll_ms() :: pos_integer
  def poll_ms, do: @poll_ms

  @html """
  <!DOCTYPE html>
  <html lang="en">
  <head>
  <meta charset="utf-8">
  <title>VWS dashboard</title>
  <meta name="viewport" content="width=device-width, initial-scale=1">
  <style>
  body { font-family: system-ui, sans-serif; margin: 0; background: #f4f5f7; color: #1d2433; }
  header { background: #1d2433; color: #fff; padding: 8px 16px; display: flex; gap: 24px; align-items: baseline; }
  header h1 { font-size: 18px; margin: 0; }
  #conn.bad { color: #ff8a80; }
  main { padding: 12px 16px; }
  section.ws { background: #fff; border-radius: 6px; padding: 8px 14px 14px; margin-bottom: 16px; box-shadow: 0 1px 3px #0002; }
  .grid { display: grid; grid-template-columns: repeat(auto-fit, minmax(520px, 1fr)); gap: 8px 24px; }
  .grid > div { min-width: 0; overflow-x: auto; }
  h2 { font-size: 17px; margin: 6px 0; } h3 { font-size: 14px; margin: 10px 0 4px; color: #4a5468; }
  table { border-collapse: collapse; width: 100%; font-size: 13px; }
  th, td { text-align: left; padding: 2px 6px; border-bottom: 1px solid #e3e6eb; vertical-align: top; }
  td.nowrap, th { white-space: nowrap; }
  th { color: #4a5468; font-weight: 600; }
  .DONE { color: #1b7a2f; } .EXECUTING { color: #b36b00; font-weight: 600; } .ERROR { color: #c62828; font-weight: 600; }
  .down, .not_answering, .restarting { color: #c62828; } .running { color: #b36b00; }
  .dialogue { font-family: ui-monospace, monospace; font-size: 12px; max-height: 260px; overflow-y: auto; background: #fafbfc; border: 1px solid #e3e6eb; padding: 4px; }
  .dialogue div { white-space: pre; }
  .muted { color: #7a8394; }
  form { display: flex; gap: 6px; flex-wrap: wrap; font-size: 13px; }
  </style>
  </head>
  <body>
  <header><h1>VWS — Vertical Workstation</h1>
  <span>updated <span id="updated">never</span></span>
  <span class="muted">updates: <span id="updates">0</span></span>
  <span id="conn"></span></header>
  <main>
  <section class="ws" id="cell" hidden><h2>Cell</h2><div id="cell-table"></div></section>
  <div id="workstations"><p class="muted">loading…</p></div>
  <section class="ws" id="control" hidden>
  <h2>Control</h2>
  <form id="control-form">
  <label>workstation <select id="control-ws"></select></label>
  <label>status command <input id="control-name" value="ROBOT_CMD" size="14"></label>
  <label>token <input id="control-token" type="password" size="16"></label>
  <button type="submit">Ask</button>
  <span id="control-answer"></span>
  </form>
  </section>
  </main>
  <script>
  "use strict";
  const POLL_MS = #{@poll_ms};
  let updates = 0;
  const seen = {};     // "ws/partition" -> "0007 EXECUTING", as last drawn
  const changes = {};  // ws -> the command status changes seen by this page, newest first

  function noteChanges(state) {
    const now = state.time.substring(11, 23);
    state.workstations.forEach(ws => {
      ws.partitions.forEach(p => {
        const key = ws.id + "/" + p.name;
        const shown = (p.number || "----") + " " + p.status;
        if (seen[key] !== undefined && seen[key] !== shown) {
          (changes[ws.id] = changes[ws.id] || []).unshift(now + "  " + p.name + ": " + seen[key] + " → " + shown);
          changes[ws.id].length = Math.min(changes[ws.id].length, 20);
        }
        seen[key] = shown;
      });
    });
  }

  function el(tag, text, cls) {
    const e = document.createElement(tag);
    if (text !== undefined && text !== null) e.textContent = String(text);
    if (cls) e.className = cls;
    return e;
  }

  function table(headers, rows) {
    const t = el("table");
    const h = el("tr");
    headers.forEach(x => h.appendChild(el("th", x)));
    t.appendChild(h);
    rows.forEach(r => {
      const tr = el("tr");
      r.forEach(c => {
        if (c && typeof c === "object") tr.appendChild(el("td", c.text, c.cls));
        else tr.appendChild(el("td", c === null || c === undefined ? "" : c));
      });
      t.appendChild(tr);
    });
    return t;
  }

  function statusClass(s) { return s ? s.split(" ")[0] : ""; }

  function box(title, content) {
    const d = el("div");
    d.appendChild(el("h3", title));
    d.appendChild(content);
    return d;
  }

  function workstation(ws) {
    const s = el("section", null, "ws");
    s.id = "ws-" + ws.id;
    s.appendChild(el("h2", "Workstation " + ws.id));
    const wc = ws.wc;
    s.appendChild(el("div", "WC link: " + wc.state + (wc.peer ? " — peer " + wc.peer : "") +
      (wc.endpoint ? " — on " + wc.endpoint : "") + " — last string " + (ws.last_sequence || "none") +
      " — " + Object.keys(wc.counters).sort().map(k => k + " " + wc.counters[k]).join(", "), "muted"));
    const g = el("div", null, "grid");
    g.appendChild(box("Partitions", table(
      ["partition", "state", "command", "status", "running", "done", "errors", "restarts"],
      ws.partitions.map(p => [p.name, {text: p.state, cls: p.state}, p.number || "----",
        {text: p.status, cls: statusClass(p.status)},
        p.current ? p.current + " (" + p.running_ms + " ms)" : "",
        p.done, p.errors, p.restarts]))));
    const devices = box("Device status", table(
      ["loc", "device", "status", "age"],
      ws.devices.map(d => [d.location, d.name, d.value === null ? "(no data)" : d.value,
        {text: d.age_ms === null ? "" : (d.age_ms < 10000 ? d.age_ms + " ms" : Math.round(d.age_ms / 1000) + " s"), cls: "nowrap"}])));
    const locks = el("div");
    locks.appendChild(box("Interlocks", ws.interlocks.length === 0 ? el("p", "none held", "muted") :
      table(["interlock", "holder"], ws.interlocks.map(i => [i.what, i.holder]))));
    locks.appendChild(box("Links", ws.links.length === 0 ? el("p", "no device links configured", "muted") :
      table(["link", "state", "details"], ws.links.map(l => [l.id, {text: l.state, cls: l.state},
        l.info.map(i => i.key + ": " + i.value).join("; ")]))));
    const dlg = el("div", null, "dialogue");
    dlg.id = "dialogue-" + ws.id;
    if (wc.dialogue.length === 0) dlg.appendChild(el("div", "no WC traffic yet", "muted"));
    wc.dialogue.forEach(l => dlg.appendChild(el("div", l.time + "  " + (l.dir === "in" ? "WC → CEC  " : "CEC → WC  ") + l.line)));
    g.appendChild(box("WC dialogue (recent)", dlg));
    const log = changes[ws.id] || [];
    locks.appendChild(box("Command status changes (seen by this page)", log.length === 0 ?
      el("p", "none yet", "muted") : (() => { const d = el("div", null, "dialogue");
        d.classList.add("changes"); log.forEach(l => d.appendChild(el("div", l))); return d; })()));
    g.appendChild(devices);
    g.appendChild(locks);
    s.appendChild(g);
    return s;
  }

  function renderCell(cell) {
    const section = document.getElementById("cell");
    section.hidden = !cell;
    if (!cell) return;
    const nodes = new Set(cell.map(w => w.node)).size;
    document.getElementById("cell-table").replaceChildren(
      el("div", cell.length + " workstation(s) on " + nodes + " node(s)", "muted"),
      table(["workstation", "node", "state", "WC link", "commands in flight"],
        cell.map(w => [w.id, w.node, {text: w.state, cls: w.state},
          w.wc ? w.wc + (w.wc_connected ? " (WC on)" : "") : "-", w.in_flight.join(", ") || "-"])));
  }

  function render(state) {
    noteChanges(state);
    renderCell(state.cell);
    const root = document.getElementById("workstations");
    const scrolls = {};
    root.querySelectorAll(".dialogue:not(.changes)").forEach(d => {
      scrolls[d.id] = d.scrollTop + d.clientHeight >= d.scrollHeight - 4 ? null : d.scrollTop;
    });
    root.replaceChildren();
    if (state.workstations.length === 0) root.appendChild(el("p", "no workstation is running on " + state.node, "muted"));
    state.workstations.forEach(ws => root.appendChild(workstation(ws)));
    root.querySelectorAll(".dialogue:not(.changes)").forEach(d => {
      d.scrollTop = (scrolls[d.id] === undefined || scrolls[d.id] === null) ? d.scrollHeight : scrolls[d.id];
    });
    const control = document.getElementById("control");
    control.hidden = !state.control;
    const sel = document.getElementById("control-ws");
    const ids = state.workstations.map(w => w.id);
    if (Array.from(sel.options).map(o => o.value).join("\\n") !== ids.join("\\n")) {
      sel.replaceChildren(...ids.map(id => { const o = el("option", id); o.value = id; return o; }));
    }
    updates += 1;
    document.getElementById("updated").textContent = state.time.replace("T", " ").replace("Z", " UTC");
    document.getElementById("updates").textContent = updates;
  }

  async function poll() {
    const conn = document.getElementById("conn");
    try {
      const r = await fetch("/api/state", {cache: "no-store"});
      if (!r.ok) throw new Error("HTTP " + r.status);
      render(await r.json());
      conn.textContent = ""; conn.className = "";
    } catch (e) {
      conn.textContent = "server not answering (" + e.message + ")"; conn.className = "bad";
    } finally {
      setTimeout(poll, POLL_MS);
    }
  }

  document.getElementById("control-form").addEventListener("submit", async ev => {
    ev.preventDefault();
    const ws = document.getElementById("control-ws").value;
    const name = document.getElementById("control-name").value;
    const out = document.getElementById("control-answer");
    const r = await fetch("/api/status?ws=" + encodeURIComponent(ws) + "&name=" + encodeURIComponent(name),
      {method: "POST", headers: {"x-vws-token": document.getElementById("control-token").value}});
    const body = await r.json();
    out.textContent = r.ok ? name + ": " + body.answer : "refused: " + body.error;
  });

  poll();
  </script>
  </body>
  </html>
  """

  @doc "The page."
  @spec html() :: String.t()
  def html, do: @html
end
