// cellbridge web: draws the frames the server pushes over /ws (no library, no build step).
// The server computes what to draw (cellbridge/views/model.py); this only paints it.
"use strict";
(() => {
  const skin = document.getElementById("skin"), sctx = skin.getContext("2d");
  const plot = document.getElementById("plot"), pctx = plot.getContext("2d");
  const conn = document.getElementById("conn");
  const token = new URLSearchParams(location.search).get("token");
  const state = {
    frame: null, ws: null, select: null, series: [], geometry: null,
    frames: 0, connects: 0, paints: [],   // paints: [wall ms, touched bridges] whenever the touched set changes (last 1000)
    lastTouched: "",
  };
  window.cellbridge = state;

  function rgb(c) { return `rgb(${c[0]},${c[1]},${c[2]})`; }

  function geometry(f) {
    const pad = 8, size = Math.min(skin.width, skin.height) - 2 * pad;
    const cell = Math.max(4, Math.floor(size / Math.max(f.rows, f.cols, 1)));
    return { pad, cell, rows: f.rows, cols: f.cols };
  }

  // CSS-pixel rectangle of an element's cell on the page (tests and the bench read it).
  state.elementRect = (bridge) => {
    const f = state.frame; if (!f) return null;
    const c = f.cells.find((c) => c.bridge === bridge); if (!c) return null;
    const g = geometry(f), box = skin.getBoundingClientRect(), k = box.width / skin.width;
    const x = g.pad + c.col * g.cell, y = g.pad + (f.rows - 1 - c.row) * g.cell;
    return { x: box.left + x * k, y: box.top + y * k, w: g.cell * k, h: g.cell * k };
  };

  // The box of a text drawn centred at (x, y) in `size` px (the canvas's current font).
  function centredBox(text, x, y, size) {
    const w = sctx.measureText(text).width;
    return { x: x - w / 2, y: y - size / 2, w, h: size };
  }

  function overlaps(a, b) {
    return a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h;
  }

  // Candidate moves of a label from its contact, nearest first (computed once).
  const MOVES = (() => {
    const m = [];
    for (let dx = -240; dx <= 240; dx += 6) for (let dy = -240; dy <= 240; dy += 6) m.push([dx, dy]);
    return m.sort((a, b) => (a[0] * a[0] + a[1] * a[1]) - (b[0] * b[0] + b[1] * b[1]));
  })();

  // Where a contact's label (w × h) goes: the place nearest the disk that covers neither the
  // disk nor any element's id or force (nor another label), inside the canvas; else right of the disk.
  function labelSpot(cx, cy, r, w, h, boxes) {
    const disk = { x: cx - r - 2, y: cy - r - 2, w: 2 * r + 4, h: 2 * r + 4 };
    const reach = { x: cx - 260 - w, y: cy - 260 - h, w: 520 + 2 * w, h: 520 + 2 * h };
    const near = boxes.filter((b) => overlaps(b, reach));
    for (const [dx, dy] of MOVES) {
      const spot = { x: cx + dx - w / 2, y: cy + dy - h / 2, w, h };
      if (spot.x < 0 || spot.y < 0 || spot.x + w > skin.width || spot.y + h > skin.height) continue;
      if (overlaps(spot, disk) || near.some((b) => overlaps(spot, b))) continue;
      return spot;
    }
    return { x: cx + r + 4, y: cy - r - 4 - h, w, h };
  }

  function drawSkin(f) {
    const g = state.geometry = geometry(f);
    const boxes = [];  // element ids and forces as drawn: contact labels keep clear of them
    sctx.clearRect(0, 0, skin.width, skin.height);
    // a skin on a robot: each patch on its own block, its link and name in the row above it
    sctx.textAlign = "left"; sctx.textBaseline = "middle";
    for (const p of f.patches || []) {
      const x = g.pad + p.col0 * g.cell, y = g.pad + (f.rows - p.row0 - p.rows) * g.cell, w = p.cols * g.cell;
      sctx.strokeStyle = "#4a5a6c"; sctx.lineWidth = 1;
      sctx.strokeRect(x - 0.5, y - 0.5, w + 1, p.rows * g.cell + 1);
      const size = Math.max(9, Math.min(13, g.cell / 3));
      sctx.font = `${size}px sans-serif`; sctx.fillStyle = "#9fb3c8";
      const room = w + g.cell * 0.8;
      let text = sctx.measureText(p.title).width <= room ? p.title : p.short;  // the name alone when narrow
      while (text.length > 1 && sctx.measureText(text).width > room) text = text.slice(0, -2) + "…";
      const ty = y - g.cell / 2;
      sctx.fillText(text, x, ty);
      boxes.push({ x, y: ty - size / 2, w: sctx.measureText(text).width, h: size });
    }
    state.patchTitles = (f.patches || []).length;
    sctx.textAlign = "center";
    for (const c of f.cells) {
      const x = g.pad + c.col * g.cell, y = g.pad + (f.rows - 1 - c.row) * g.cell;
      sctx.fillStyle = rgb(c.rgb);
      sctx.fillRect(x + 1, y + 1, g.cell - 2, g.cell - 2);
      if (c.bridge === state.select) { sctx.strokeStyle = "#fff"; sctx.lineWidth = 2; sctx.strokeRect(x + 2, y + 2, g.cell - 4, g.cell - 4); }
      const lum = 0.299 * c.rgb[0] + 0.587 * c.rgb[1] + 0.114 * c.rgb[2];
      sctx.fillStyle = lum > 140 ? "#000" : "#fff";
      if (g.cell >= 40) {
        const size = Math.max(9, g.cell / 9), tx = x + g.cell * 0.14, ty = y + g.cell * 0.12;
        sctx.font = `${size}px sans-serif`;
        sctx.fillText(String(c.bridge), tx, ty);
        boxes.push(centredBox(String(c.bridge), tx, ty, size));
      }
      if (g.cell >= 24 && c.label) {
        const size = Math.max(9, g.cell / 6), tx = x + g.cell / 2, ty = y + g.cell * 0.3;
        sctx.font = `${size}px sans-serif`;
        sctx.fillText(c.label, tx, ty);
        boxes.push(centredBox(c.label, tx, ty, size));
      }
    }
    const shown = [];
    for (const k of f.contacts) {
      if (k.col === null || k.row === null) continue;
      const cx = g.pad + k.col * g.cell, cy = g.pad + (f.rows - k.row) * g.cell;
      const r = Math.max(4, (k.diameter || 0) * g.cell / 2);
      shown.push([k, cx, cy, r]);
      sctx.beginPath(); sctx.arc(cx, cy, r, 0, 2 * Math.PI);
      sctx.fillStyle = `rgba(${k.rgb[0]},${k.rgb[1]},${k.rgb[2]},0.85)`; sctx.fill();
      sctx.lineWidth = 2; sctx.strokeStyle = "#fff"; sctx.setLineDash(k.observable[0] && k.observable[1] ? [] : [4, 3]); sctx.stroke(); sctx.setLineDash([]);
      if (!k.observable[0]) { sctx.beginPath(); sctx.moveTo(cx - g.cell / 2, cy); sctx.lineTo(cx + g.cell / 2, cy); sctx.stroke(); }
      if (!k.observable[1]) { sctx.beginPath(); sctx.moveTo(cx, cy - g.cell / 2); sctx.lineTo(cx, cy + g.cell / 2); sctx.stroke(); }
    }
    // labels after every disk, each on a dark backing, clear of the elements' own text
    sctx.font = "bold 14px sans-serif"; sctx.textAlign = "left";
    for (const [i, [k, cx, cy, r]] of shown.entries()) {
      const text = `${k.label} ⌀${k.diameter_m === null ? "?" : (k.diameter_m * 1e3).toFixed(1)} mm`;
      const w = sctx.measureText(text).width + 6, h = 18;
      const spot = i < 16 ? labelSpot(cx, cy, r, w, h, boxes) : { x: cx + r + 4, y: cy - r - 4 - h, w, h };
      sctx.fillStyle = "rgba(0,0,0,0.6)"; sctx.fillRect(spot.x, spot.y, w, h);
      sctx.fillStyle = "#fff"; sctx.fillText(text, spot.x + 3, spot.y + h / 2);
      boxes.push(spot);
    }
    sctx.textAlign = "center";
    document.getElementById("legend").textContent =
      `colour: ${f.quantity === "force" ? "force" : "ΔC1 (no force yet)"}, full at ${f.scale} ${f.quantity === "force" ? "N" : "pF"}` +
      (f.live ? "" : "  (daemon silent)");
  }

  function drawContacts(f) {
    const ul = document.getElementById("contacts");
    ul.replaceChildren(...(f.contacts.length ? f.contacts.map((k) => {
      const li = document.createElement("li"); li.textContent = k.line; li.dataset.id = k.id; return li;
    }) : [Object.assign(document.createElement("li"), { className: "none", textContent: "no contact" })]));
  }

  function drawPlot() {
    const w = plot.width, h = plot.height, pts = state.series;
    pctx.clearRect(0, 0, w, h);
    pctx.strokeStyle = "#334"; pctx.strokeRect(0.5, 0.5, w - 1, h - 1);
    if (!pts.length) return;
    const t1 = pts[pts.length - 1][0], t0 = t1 - 10;
    const useForce = pts.some((p) => p[1] !== null);
    const vals = pts.map((p) => useForce ? p[1] : p[2]).filter((v) => v !== null);
    const vmax = Math.max(0.5, ...vals) * 1.1;
    pctx.strokeStyle = "#f0c828"; pctx.lineWidth = 1.5; pctx.beginPath();
    let pen = false;
    for (const p of pts) {
      const v = useForce ? p[1] : p[2];
      if (v === null || p[0] < t0) { pen = false; continue; }
      const x = (p[0] - t0) / 10 * w, y = h - v / vmax * (h - 10) - 5;
      if (pen) pctx.lineTo(x, y); else pctx.moveTo(x, y); pen = true;
    }
    pctx.stroke();
    pctx.fillStyle = "#9fb3c8"; pctx.font = "11px sans-serif"; pctx.textAlign = "left";
    pctx.fillText(`${vmax.toFixed(2)} ${useForce ? "N" : "pF"}`, 4, 12);
    pctx.fillText("last 10 s", 4, h - 4);
  }

  function onFrame(f) {
    state.frame = f; state.frames++;
    if (f.series) {
      if (f.series.reset) state.series = [];
      state.series.push(...f.series.points);
      if (state.series.length > 4000) state.series.splice(0, state.series.length - 4000);
    }
    requestAnimationFrame(() => {
      drawSkin(f); drawContacts(f); drawPlot();
      document.getElementById("status").textContent = f.status.join("\n") +
        `\npage: ${state.frames} frames, ${state.connects} connections`;
      const touched = f.cells.filter((c) => c.touched).map((c) => c.bridge).join(",");
      if (touched !== state.lastTouched) {
        if (state.paints.length >= 1000) state.paints.shift();
        state.lastTouched = touched;
        // a task queued in the frame's callback runs once that frame is rendered
        setTimeout(() => state.paints.push([performance.timeOrigin + performance.now(), touched]), 0);
      }
    });
  }

  skin.addEventListener("click", (ev) => {
    const f = state.frame, g = state.geometry; if (!f || !g) return;
    const box = skin.getBoundingClientRect(), k = skin.width / box.width;
    const col = Math.floor(((ev.clientX - box.left) * k - g.pad) / g.cell);
    const row = f.rows - 1 - Math.floor(((ev.clientY - box.top) * k - g.pad) / g.cell);
    const c = f.cells.find((c) => c.col === col && c.row === row);
    state.select = c ? c.bridge : null; state.series = [];
    document.getElementById("selected").textContent = c ? `bridge ${c.bridge}` : "(click one)";
    if (state.ws && state.ws.readyState === 1) state.ws.send(JSON.stringify({ select: state.select }));
  });

  let backoff = 250;
  function connect() {
    const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${token ? "?token=" + encodeURIComponent(token) : ""}`;
    const ws = state.ws = new WebSocket(url);
    ws.onopen = () => {
      backoff = 250; state.connects++;
      conn.textContent = "live"; conn.className = "ok";
      if (state.select !== null) ws.send(JSON.stringify({ select: state.select }));
    };
    ws.onmessage = (ev) => {
      const f = JSON.parse(ev.data);
      if (f.type === "frame") {
        onFrame(f);
        conn.textContent = f.live ? "live" : "daemon silent"; conn.className = f.live ? "ok" : "bad";
      }
    };
    ws.onclose = () => {
      conn.textContent = "server gone: reconnecting…"; conn.className = "bad";
      setTimeout(connect, backoff); backoff = Math.min(5000, backoff * 2);
    };
  }
  connect();
})();
