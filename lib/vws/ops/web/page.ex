defmodule Vws.Ops.Web.Page do
  @moduledoc """
  The dashboard: one HTML page with plain JavaScript that asks `/api/state` (`Vws.Ops.Web.State`)
  every 400 ms and redraws, per workstation: what is wrong now and the errors seen recently
  (highlighted); the partitions with their state, command and status; the numbers read from
  the sensors (jaw width, finger gap, vise and pallet clamp forces, …) each with a small trend
  plot of its last values (an inline SVG drawn by the page from a history it keeps, up to
  150 polls); the device statuses as the WC reads them; every link (the WC link, DAQ #1,
  the hydraulic controller, the GE-2000, the VAL II) with its state, counters, retries and last
  error; the interlock leases; NC transfers under way with their progress, rate and ETA; the
  last drip feed restarted at a line, with the preamble that restores its modal state; the
  recent WC dialogue and the node's recent events (`Vws.Ops.Web.History`: command status changes
  and operator actions, each with the node's time, so a reload keeps them). Below them the equipment on this
  node outside any workstation (the hydraulic controller with its link to DAQ #2), and, on a
  node of a cell, the cell: every workstation of every connected node with its state.

  Text from the equipment is only ever put into the page with `textContent`, never as HTML.
  Colours come from the server's severity (`Vws.Ops.Web.State.severity/1`): red only for errors,
  grey for what is not read yet. Sensor numbers are shown as the CEC judges them (deadbanded);
  `?raw=1` or the "raw values" box shows them as read.

  The control form (a status query) appears only when the server has a control token, and
  sends the token the user types in the `x-vws-token` header. Once a token is typed, the
  operator commands (`Vws.Ops.Web.Command`) appear: a set, a command text (presets fill it) and
  Send; the answer line follows the command's status until it ends DONE or ERROR. A link may
  carry `#token=…&ws=…&set=M&text=DRIP_FEED` in its fragment: the page fills the form and
  sends it, as a click on Send does.
  """

  @poll_ms 400
  @history 150

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
  td.nowrap, th { white-space: nowrap; } td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
  th { color: #4a5468; font-weight: 600; }
  .done { color: #1b7a2f; } .executing { color: #b36b00; font-weight: 600; } .error { color: #c62828; font-weight: 600; }
  .bad, .down, .not_answering, .unreadable { color: #c62828; } .running, .restarting, .connecting { color: #b36b00; }
  .warning { color: #b36b00; font-weight: 600; } .neutral { color: #7a8394; } .ok { color: inherit; }
  .alerts { border: 1px solid #f2b8b5; background: #fdecea; border-radius: 4px; padding: 4px 8px; font-size: 13px; }
  .alerts div.new { font-weight: 700; }
  .alerts .none { color: #1b7a2f; }
  .ok-box { border: 1px solid #c8e6c9; background: #eef8ef; border-radius: 4px; padding: 4px 8px; font-size: 13px; color: #1b7a2f; }
  .dialogue { font-family: ui-monospace, monospace; font-size: 12px; max-height: 260px; overflow-y: auto; background: #fafbfc; border: 1px solid #e3e6eb; padding: 4px; }
  .dialogue div { white-space: pre; }
  .muted { color: #7a8394; }
  .counters { font-size: 12px; color: #4a5468; }
  svg.spark { vertical-align: middle; }
  .bar { display: inline-block; width: 160px; height: 10px; background: #e3e6eb; border-radius: 5px; overflow: hidden; vertical-align: middle; }
  .bar > span { display: block; height: 100%; background: #3f6fd8; }
  .switches span { display: inline-block; margin: 0 10px 2px 0; font-size: 12px; }
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
  <section class="ws" id="equipment" hidden><h2>Equipment on this node</h2><div id="equipment-table"></div></section>
  <section class="ws" id="control" hidden>
  <h2>Control</h2>
  <form id="control-form">
  <label>workstation <select id="control-ws"></select></label>
  <label>token <input id="control-token" type="password" size="16"></label>
  <label>status command <input id="control-name" value="ROBOT_CMD" size="14"></label>
  <button type="submit">Ask</button>
  <span id="control-answer"></span>
  </form>
  <div id="actions" hidden>
  <h3>Operator commands (through SUN_COMM, as a WC's)</h3>
  <form id="command-form">
  <label>set <select id="command-set"><option value="M">M (MONARCH)</option><option value="R">R (ROBOT)</option><option value="F">F (FIXTURE)</option></select></label>
  <label>command <input id="command-text" size="28" placeholder="DOWNLOAD_GE(001234.PRO/2)"></label>
  <button type="submit" id="command-send">Send</button>
  </form>
  <div id="command-presets"></div>
  <div id="command-answer"></div>
  </div>
  </section>
  </main>
  <script>
  "use strict";
  const POLL_MS = #{@poll_ms};
  const HISTORY = #{@history};
  let updates = 0;
  const history = {};  // "ws/key" -> the last HISTORY values of a sensor quantity (null: no reading)
  const errors = {};   // ws -> recent errors seen by this page: {first, last, where, text}, newest first

  function noteChanges(state) {
    const now = state.time.substring(11, 23);
    const t = Date.parse(state.time);
    state.workstations.forEach(ws => {
      const qs = (ws.sensors && ws.sensors.quantities) || [];
      qs.forEach(q => {
        const h = history[ws.id + "/" + q.key] = history[ws.id + "/" + q.key] || [];
        h.push(raw ? q.raw : q.value);
        if (h.length > HISTORY) h.shift();
      });
      const log = errors[ws.id] = errors[ws.id] || [];
      (ws.alerts || []).slice().reverse().forEach(a => {
        const found = log.find(e => e.where === a.where && e.text === a.text);
        if (found) { found.last = t; found.lastText = now; }
        else log.unshift({first: t, firstText: now, last: t, lastText: now, where: a.where, text: a.text, severity: a.severity});
      });
      log.length = Math.min(log.length, 30);
    });
  }

  function el(tag, text, cls) {
    const e = document.createElement(tag);
    if (text !== undefined && text !== null) e.textContent = String(text);
    if (cls) e.className = cls;
    return e;
  }

  function table(headers, rows, id) {
    const t = el("table");
    if (id) t.id = id;
    const h = el("tr");
    headers.forEach(x => h.appendChild(el("th", x)));
    t.appendChild(h);
    rows.forEach(r => {
      const tr = el("tr");
      r.forEach(c => {
        if (c instanceof Node) { const td = el("td"); td.appendChild(c); tr.appendChild(td); }
        else if (c && typeof c === "object") tr.appendChild(el("td", c.text, c.cls));
        else tr.appendChild(el("td", c === null || c === undefined ? "" : c));
      });
      t.appendChild(tr);
    });
    return t;
  }

  function box(title, content) {
    const d = el("div");
    d.appendChild(el("h3", title));
    d.appendChild(content);
    return d;
  }

  function age(ms) {
    if (ms === null || ms === undefined) return "";
    return ms < 10000 ? ms + " ms" : Math.round(ms / 1000) + " s";
  }

  // A small trend plot of a quantity's recent values: an SVG polyline, gaps where no reading.
  function spark(values) {
    const NS = "http://www.w3.org/2000/svg", W = 150, H = 26;
    const svg = document.createElementNS(NS, "svg");
    svg.setAttribute("width", W); svg.setAttribute("height", H);
    svg.setAttribute("class", "spark");
    const nums = values.filter(v => typeof v === "number");
    if (nums.length === 0) return svg;
    let lo = Math.min(...nums), hi = Math.max(...nums);
    // a steady value stays a flat line: its noise is not blown up to the plot's height
    const least = Math.max(1, 0.05 * Math.max(Math.abs(hi), Math.abs(lo)));
    if (hi - lo < least) { const mid = (hi + lo) / 2; lo = mid - least / 2; hi = mid + least / 2; }
    const span = Math.max(values.length, 30) - 1;
    const x = i => (i * (W - 2)) / span + 1;
    const y = v => H - 2 - ((v - lo) * (H - 4)) / (hi - lo);
    let pts = [];
    const flush = () => {
      if (pts.length > 0) {
        const p = document.createElementNS(NS, "polyline");
        p.setAttribute("points", pts.join(" "));
        p.setAttribute("fill", "none"); p.setAttribute("stroke", "#3f6fd8"); p.setAttribute("stroke-width", "1.5");
        svg.appendChild(p);
      }
      pts = [];
    };
    values.forEach((v, i) => { if (typeof v === "number") pts.push(x(i).toFixed(1) + "," + y(v).toFixed(1)); else flush(); });
    flush();
    return svg;
  }

  // as the CEC judges it (deadbanded by the server), or as read with ?raw=1 or the toggle
  const RAW = new URLSearchParams(location.search).get("raw") === "1";
  let raw = RAW;
  function value(q) {
    if (q.value === null || q.value === undefined) return {text: "no reading" + (q.note ? " (" + q.note + ")" : ""), cls: "num neutral"};
    if (raw) return {text: q.raw + " " + q.unit + " (raw)", cls: "num"};
    const v = q.value === 0 ? 0 : q.value;  // never "-0.0"
    return {text: (q.unit === "N" ? Math.round(v) : v.toFixed(1)) + " " + q.unit, cls: "num"};
  }

  function sensors(ws) {
    const s = ws.sensors;
    const d = el("div");
    d.appendChild(el("div", s.poll !== null ? "DAQ #1 poll " + s.poll + ", " + age(s.age_ms) + " ago" :
      (s.note || "no readings"), "muted"));
    d.appendChild(table(["quantity", "value", "trend", "from"],
      s.quantities.map(q => [q.name, value(q), spark(history[ws.id + "/" + q.key] || []), q.source]), "sensors-" + ws.id));
    const t = el("label", null, "muted");
    const box = el("input"); box.type = "checkbox"; box.checked = raw; box.className = "raw-toggle";
    box.addEventListener("change", () => { raw = box.checked; });
    t.appendChild(box); t.appendChild(document.createTextNode(" raw values"));
    d.appendChild(t);
    const sw = el("div", null, "switches");
    s.switches.forEach(x => sw.appendChild(el("span", x.name + ": " + x.state)));
    d.appendChild(sw);
    return d;
  }

  function counters(list) {
    return list.filter(c => c.value !== 0).map(c => c.key + " " + c.value).join(", ");
  }

  function linkRows(ws) {
    const wc = ws.wc;
    const rows = [["WC (SUN_COMM)", {text: wc.state, cls: wc.state === "connected" || wc.state === "waiting" ? "" : "bad"},
      {text: wc.retries, cls: "num"}, "",
      {text: Object.keys(wc.counters).sort().filter(k => wc.counters[k] !== 0).map(k => k.replace(/_/g, " ") + " " + wc.counters[k]).join(", "), cls: "counters"},
      (wc.peer ? "peer " + wc.peer : "no peer") + (wc.endpoint ? ", on " + wc.endpoint : "") + ", mode " + wc.mode]];
    return rows.concat(ws.links.map(linkRow));
  }

  function linkRow(l) {
    return [l.id, {text: l.state, cls: l.severity || l.state_class}, {text: l.retries, cls: "num"},
      {text: l.last_error || "", cls: l.last_error ? (l.severity === "error" ? "error" : "warning") : ""},
      {text: counters(l.counters), cls: "counters"}, l.details];
  }

  const LINK_HEAD = ["link", "state", "retries", "last error", "counters", "details"];

  function transfers(ws) {
    if (ws.transfers.length === 0) return el("p", "no NC transfer under way", "muted");
    return table(["transfer", "link", "progress", "so far", "rate", "ETA"], ws.transfers.map(t => {
      const bar = el("span", null, "bar");
      const fill = el("span"); fill.style.width = (t.percent === null ? 0 : t.percent) + "%"; bar.appendChild(fill);
      const prog = el("span"); prog.appendChild(bar); prog.appendChild(el("span", t.percent === null ? " length not announced" : " " + t.percent + " %"));
      const what = [t.kind, t.number, t.program, t.version ? "v" + t.version : null].filter(x => x).join(" ");
      return [what, t.link, prog,
        t.done + (t.total !== null ? " of " + t.total : "") + " " + t.unit + ", " + t.bytes + (t.total_bytes !== null ? " of " + t.total_bytes : "") + " bytes",
        {text: t.bytes_per_s + " B/s", cls: "num"}, {text: t.eta_s === null ? "unknown" : t.eta_s + " s", cls: "num"}];
    }), "transfers-" + ws.id);
  }

  // The last drip feed restarted at a line: the preamble that restores the modal state of the
  // lines before it, told by MONARCH before the first block went (issue 27).
  function restart(ws) {
    const r = ws.restart;
    const d = el("div");
    d.id = "restart-" + ws.id;
    d.appendChild(el("div", r.program + " version " + r.version + " restarted at line " + r.line + " — " +
      r.time.replace("T", " ").replace("Z", "") + " UTC — restored preamble, sent before line " + r.line + ":", "muted"));
    const pre = el("div", null, "dialogue");
    pre.classList.add("changes");
    (r.preamble.length ? r.preamble : ["(none: the program's head only)"]).forEach(l => pre.appendChild(el("div", l)));
    d.appendChild(pre);
    return d;
  }

  function library(ws) {
    const l = ws.library;
    if (!l) return el("p", "no program library", "muted");
    if (l.error) return el("p", l.error, "bad");
    const d = el("div");
    const c = l.counts;
    d.appendChild(el("div", l.programs + " programs, " + l.versions + " versions — on the machine: " +
      (c.same || 0) + " same, " + (c.differs || 0) + " differ, " + (c.absent || 0) + " absent" +
      (c.ambiguous ? ", " + c.ambiguous + " to read back" : "") +
      (l.machine_only.length ? ", " + l.machine_only.length + " only on the machine" : "") +
      " — " + (l.read_at ? "machine directory read " + l.read_at : "machine directory not read yet"), "muted"));
    if (l.rows.length) d.appendChild(table(["program", "versions", "latest", "stored", "by", "bytes", "CRC", "on the machine"],
      l.rows.map(r => [r.name, {text: r.versions, cls: "num"}, "v" + r.latest + (r.note ? " (" + r.note + ")" : ""), r.at, r.source, {text: r.size, cls: "num"}, r.crc,
        {text: r.on_machine, cls: r.on_machine_class === "same" ? "" : (r.on_machine_class === "unknown" ? "muted" : "bad")}]),
      "library-" + ws.id));
    return d;
  }

  function transferHistory(ws) {
    const h = ws.library && ws.library.history;
    if (!h) return el("p", "no program library", "muted");
    const d = el("div");
    if (h.damaged) d.appendChild(el("div", h.damaged + " damaged part(s) of the history skipped (see the log)", "bad"));
    if (h.rows.length === 0) { d.appendChild(el("p", "no transfers recorded yet", "muted")); return d; }
    d.appendChild(table(["when", "program", "direction", "command", "bytes", "blocks", "ms", "B/s", "retries", "result", "by", "found"],
      h.rows.map(r => [r.at, r.program, r.direction, r.command, {text: r.bytes, cls: "num"}, {text: r.blocks, cls: "num"},
        {text: r.ms, cls: "num"}, {text: r.chars_per_s, cls: "num"}, {text: r.retries, cls: "num"},
        {text: r.result, cls: r.severity === "ok" ? "" : "bad"}, r.requester, r.note]), "transfer-history-" + ws.id));
    return d;
  }

  function alerts(ws) {
    const log = errors[ws.id] || [];
    const now = Date.now();
    const current = new Set((ws.alerts || []).map(a => a.where + "|" + a.text));
    if (log.length === 0) return el("div", "no errors seen", "ok-box");
    if (!log.some(e => e.severity === "error")) {
      const w = el("div", null, "ok-box"); w.id = "alerts-" + ws.id;
      log.forEach(e => w.appendChild(el("div", e.firstText + "  " + e.where + ": " + e.text, current.has(e.where + "|" + e.text) ? "warning" : "muted")));
      return w;
    }
    const d = el("div", null, "alerts");
    d.id = "alerts-" + ws.id;
    log.forEach(e => {
      const still = current.has(e.where + "|" + e.text);
      const line = el("div", e.firstText + "  " + e.where + ": " + e.text + (still ? "  (now)" : "  (until " + e.lastText + ")"),
        (still ? (e.severity || "error") : "muted") + (now - e.first < 15000 ? " new" : ""));
      d.appendChild(line);
    });
    return d;
  }

  function workstation(ws) {
    const s = el("section", null, "ws");
    s.id = "ws-" + ws.id;
    s.appendChild(el("h2", "Workstation " + ws.id));
    if (ws.unreadable) s.appendChild(el("p", ws.unreadable, "bad"));
    const wc = ws.wc;
    s.appendChild(el("div", "WC link: " + wc.state + (wc.peer ? " — peer " + wc.peer : "") +
      (wc.endpoint ? " — on " + wc.endpoint : "") + " — last string " + (ws.last_sequence || "none"), "muted"));
    s.appendChild(box("Errors (now and recent)", alerts(ws)));
    const g = el("div", null, "grid");
    g.appendChild(box("Partitions", table(
      ["partition", "state", "command", "status", "running", "done", "errors", "restarts", "link"],
      ws.partitions.map(p => [p.name, {text: p.state, cls: p.state}, p.number || "----",
        {text: p.status, cls: p.severity === "ok" ? p.status_class : p.severity},
        p.current ? p.current + " (" + p.running_ms + " ms)" : "",
        p.done, p.errors, p.restarts, p.link]), "partitions-" + ws.id)));
    g.appendChild(box("Sensors (numbers as read, with their trend)", sensors(ws)));
    g.appendChild(box("Device status (as the WC reads it)", table(
      ["loc", "device", "status", "age"],
      ws.devices.map(d => [d.location, d.name, {text: d.value === null ? "(never written)" : d.value, cls: d.severity}, 
        {text: age(d.age_ms), cls: "nowrap"}]), "devices-" + ws.id)));
    const right = el("div");
    right.appendChild(box("NC transfers", transfers(ws)));
    if (ws.restart) right.appendChild(box("Drip-feed restart (MONARCH)", restart(ws)));
    right.appendChild(box("Program library", library(ws)));
    right.appendChild(box("Transfer history (newest first)", transferHistory(ws)));
    right.appendChild(box("Interlock leases", ws.interlocks.length === 0 ? el("p", "none held", "muted") :
      table(["volume", "holder", "for", "held"], ws.interlocks.map(i => [i.what, i.holder, i.reasons, age(i.age_ms)]), "interlocks-" + ws.id)));
    const hist = (ws.history || []).slice().reverse();
    right.appendChild(box("Recent events (the node's time, UTC)", hist.length === 0 ?
      el("p", "none yet", "muted") : (() => { const d = el("div", null, "dialogue");
        d.classList.add("changes"); d.id = "history-" + ws.id;
        hist.forEach(e => d.appendChild(el("div", e.time.replace("T", " ").replace("Z", "") + "  " + e.where + ": " + e.text,
          e.severity === "ok" ? "" : e.severity))); return d; })()));
    g.appendChild(right);
    s.appendChild(g);
    s.appendChild(box("Links", table(LINK_HEAD, linkRows(ws), "links-" + ws.id)));
    const dlg = el("div", null, "dialogue");
    dlg.id = "dialogue-" + ws.id;
    if (wc.dialogue.length === 0) dlg.appendChild(el("div", "no WC traffic yet", "muted"));
    wc.dialogue.forEach(l => dlg.appendChild(el("div", l.time + "  " + (l.dir === "in" ? "WC → CEC  " : "CEC → WC  ") + l.line)));
    s.appendChild(box("WC dialogue (recent)", dlg));
    return s;
  }

  function renderEquipment(list) {
    const section = document.getElementById("equipment");
    section.hidden = !list || list.length === 0;
    if (section.hidden) return;
    const rows = [];
    list.forEach(e => {
      rows.push([e.name, {text: e.state, cls: e.state}, "", "", "", (e.status ? "status " + e.status + ", " : "") + e.details]);
      e.links.forEach(l => rows.push(linkRow(l)));
    });
    document.getElementById("equipment-table").replaceChildren(table(LINK_HEAD, rows, "equipment-links"));
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
    renderEquipment(state.equipment);
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
    if (Array.from(sel.options).map(o => o.value).join(",") !== ids.join(",")) {
      sel.replaceChildren(...ids.map(id => { const o = el("option", id); o.value = id; return o; }));
    }
    showPending(state);
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

  // Operator commands: sent with the token to /api/command; the answer line follows the
  // command's status location (from /api/state) until it ends DONE or ERROR.
  const PARTITION = {M: "MONARCH", R: "ROBOT", F: "FIXTURE"};
  const PRESETS = [["M", "DOWNLOAD_GE(000000.PRO/1)"], ["M", "COMPARE_GE(000000.PRO)"], ["M", "UPLOAD_GE(000000.PRO)"],
    ["M", "DRIP_FEED"], ["M", "DRIP_FEED(000000.PRO)"], ["M", "DRIP_FEED(000000.PRO/1/N1)"], ["R", "RELEASE_TABLE"], ["F", "RELEASE_TABLE"], ["M", "RELEASE_TABLE"], ["R", "RELEASE_TRAY1"], ["R", "RELEASE_TRAY2"]];
  let pending = null;  // {ws, set, number, text, status}

  function showPending(state) {
    const tokenGiven = document.getElementById("control-token").value !== "";
    document.getElementById("actions").hidden = !(state.control && tokenGiven);
    if (!pending || pending.ended) return;
    // a state read before the command was taken (a poll on its way when it was sent) says nothing
    // of it: a WC command before it would look like one after it (the numbers wrap)
    if (pending.time && !(state.time > pending.time)) return;
    const ws = state.workstations.find(w => w.id === pending.ws);
    const p = ws && ws.partitions.find(x => x.name === PARTITION[pending.set]);
    if (!p) return;
    if (p.number === pending.number) pending.status = p.status;
    else if (pending.status === "EXECUTING" && later(p.number, pending.number)) pending.status = "(status location now " + p.number + ")";
    pending.ended = /^(DONE|ERROR)/.test(pending.status);
    drawPending();
  }

  // A number after `than` (4 digits, wrapping): a state read before the command was taken still
  // shows the number before it, and must not end the following.
  function later(number, than) {
    const d = (parseInt(number, 10) - parseInt(than, 10) + 10000) % 10000;
    return d > 0 && d < 5000;
  }

  function drawPending() {
    const out = document.getElementById("command-answer");
    const cls = /^ERROR/.test(pending.status) ? "error" : (pending.status === "DONE" ? "done" : "executing");
    out.replaceChildren(el("span", pending.set + pending.number + " " + pending.text + ": " + pending.status, cls));
    out.firstChild.id = "command-status";
  }

  const presets = document.getElementById("command-presets");
  PRESETS.forEach(([set, text]) => {
    const b = el("button", set + " " + text); b.type = "button";
    b.addEventListener("click", () => { document.getElementById("command-set").value = set; document.getElementById("command-text").value = text; });
    presets.appendChild(b);
  });

  document.getElementById("control-token").addEventListener("input", () => {
    document.getElementById("actions").hidden = document.getElementById("control-token").value === "" || document.getElementById("control").hidden;
  });

  document.getElementById("command-form").addEventListener("submit", async ev => {
    ev.preventDefault();
    const body = {workstation: document.getElementById("control-ws").value, set: document.getElementById("command-set").value,
      text: document.getElementById("command-text").value};
    const out = document.getElementById("command-answer");
    const r = await fetch("/api/command", {method: "POST", body: JSON.stringify(body),
      headers: {"x-vws-token": document.getElementById("control-token").value, "content-type": "application/json"}});
    const a = await r.json();
    if (!r.ok) { pending = null; out.replaceChildren(el("span", "refused: " + a.error, "error")); out.firstChild.id = "command-status"; return; }
    pending = {ws: a.workstation, set: a.set, number: a.number, text: a.text, status: a.status, time: a.time, ended: false};
    pending.ended = /^(DONE|ERROR)/.test(pending.status);
    drawPending();
  });

  // A link may carry the token and one command in its fragment (never sent to the server):
  // #token=…&set=M&text=DRIP_FEED fills the form and sends it, as a click on Send does.
  (function fromFragment() {
    const f = new URLSearchParams(location.hash.substring(1));
    if (!f.get("token")) return;
    document.getElementById("control-token").value = f.get("token");
    if (!f.get("text")) return;
    const go = () => {
      const sel = document.getElementById("control-ws");
      const want = f.get("ws") || (sel.options[0] && sel.options[0].value);
      if (!want || !Array.from(sel.options).some(o => o.value === want)) { setTimeout(go, 100); return; }
      sel.value = want;
      document.getElementById("command-set").value = f.get("set") || "M";
      document.getElementById("command-text").value = f.get("text");
      document.getElementById("command-send").click();
    };
    setTimeout(go, 500);
  })();

  poll();
  </script>
  </body>
  </html>
  """

  @doc "The page."
  @spec html() :: String.t()
  def html, do: @html
end
