// The shapeloc live view: draws what the server pushes over /ws on a 2D canvas.
// Messages: "hello" (colours, rates), "maps" (every map's polylines), "frame" (the robots that
// changed, or every robot when "key" is true; "path" in a snapshot, "trail" = positions added
// since the previous frame). Map frame: x right, y up (REP 103); the canvas is y down, so y is
// flipped when drawn.
// Cheap by design (the browser may share the robot server's cores): the maps are drawn once
// into an offscreen canvas and copied; the canvas is redrawn only when new data arrived, at
// most MAX_DRAW_HZ times a second, on an animation frame; at most MAX_SCAN_POINTS points per
// scan; the side panel is refreshed at most PANEL_HZ times a second.
// window.shapelocView exposes the state (frames, update rate, what was drawn where) so that a
// test driving a headless browser can check the picture against the published poses.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const canvas = $("canvas");
  const ctx = canvas.getContext("2d");
  const MAX_DRAW_HZ = 10;
  const PANEL_HZ = 2;
  const MAX_SCAN_POINTS = 180;

  const S = {
    palette: null,
    maps: {},
    mapId: null,
    overlayId: "",
    userPickedMap: false,
    robots: new Map(),
    hidden: new Set(),
    view: null,
    pathLen: 300,
    staleS: 3,
    time: 0,
    frames: 0,
    draws: 0,
    frameTimes: [],
    rate: 0,
    lastFrame: null,
    connected: false,
    drawn: {},
    lastSelect: null,
    errors: [],
  };
  window.shapelocView = S;

  // Optional query parameters: ?map=ID&overlay=ID&robots=a,b (the robots drawn; default all).
  const params = new URLSearchParams(location.search);
  const wantMap = params.get("map");
  let wantOverlay = params.get("overlay") || "";
  const wantRobots = params.get("robots") ? new Set(params.get("robots").split(",")) : null;

  // ------------------------------------------------------------------ colours
  function statusColour(st) {
    const p = S.palette;
    if (!p) return "#8c8c8c";
    const e = p.status[st];
    return e ? e.colour : p.unknown;
  }
  function statusLabel(st) {
    const p = S.palette;
    const e = p && p.status[st];
    return e ? e.label : (st || "no pose");
  }
  function buildLegend() {
    const p = S.palette;
    const el = $("legend");
    el.textContent = "";
    const add = (colour, text, cls) => {
      const s = document.createElement("span");
      const d = document.createElement("i");
      d.className = cls;
      d.style.background = colour;
      s.append(d, text);
      el.append(s);
    };
    for (const st of Object.keys(p.status)) add(p.status[st].colour, p.status[st].label, "dot");
    add(p.unknown, "other", "dot");
    add(p.scan, "scan at pose", "sq");
    add(p.candidate, "candidate", "sq");
  }

  // ------------------------------------------------------------------ messages
  function onHello(m) {
    S.palette = m.palette;
    S.pathLen = m.path_len || 300;
    S.staleS = m.stale_s || 3;
    buildLegend();
  }

  function onMaps(m) {
    S.mapsVersion = (S.mapsVersion || 0) + 1;
    S.maps = {};
    for (const mp of m.maps) S.maps[mp.id] = mp;
    if (S.mapId && !S.maps[S.mapId]) { S.mapId = null; S.userPickedMap = false; }
    if (S.overlayId && !S.maps[S.overlayId]) S.overlayId = "";
    fillMapSelects();
    chooseMap();
    requestDraw();
  }

  // Robots with a pose younger than maxAge seconds at the last frame's time.
  S.fresh = (maxAge) => {
    let n = 0;
    for (const r of S.robots.values()) if (r.seenAt !== undefined && S.time - r.seenAt < maxAge) n += 1;
    return n;
  };

  let newData = false;
  function onFrame(m) {
    const seen = new Set();
    for (const e of m.robots) {
      seen.add(e.id);
      let r = S.robots.get(e.id);
      if (!r) {
        r = { id: e.id, path: [], scan: null };
        S.robots.set(e.id, r);
        if (wantRobots && !wantRobots.has(e.id)) S.hidden.add(e.id);
      }
      if (e.path) r.path = e.path.slice(-S.pathLen);
      else if (e.trail && e.trail.length) {
        if (r.map !== undefined && e.map !== r.map) r.path = [];
        for (const p of e.trail) r.path.push(p);
        if (r.path.length > S.pathLen) r.path.splice(0, r.path.length - S.pathLen);
      }
      for (const k of ["map", "status", "seq", "x", "y", "th", "lat", "score", "method",
        "age", "stale", "explained", "ambiguity", "hyp", "cand", "cov", "hz"]) {
        r[k] = e[k];
      }
      if (e.age !== undefined) r.seenAt = m.time - e.age;
      // a frame without the scan keeps the one held if it is still the pose's
      if (e.scan) r.scan = e.scan;
      else if (r.scan && r.scan.seq !== r.seq) r.scan = null;
    }
    if (m.key) for (const id of [...S.robots.keys()]) if (!seen.has(id)) S.robots.delete(id);
    S.time = m.time;
    S.lastFrame = m;
    chooseMap();
    newData = true;
    requestDraw();
  }

  // ------------------------------------------------------------------ map choice
  function robotsOn(mapId) {
    let n = 0;
    for (const r of S.robots.values()) if (r.map === mapId) n += 1;
    return n;
  }
  function chooseMap() {
    const ids = Object.keys(S.maps).sort();
    if (!ids.length) return;
    if (wantOverlay && S.maps[wantOverlay] && wantOverlay !== (wantMap || S.mapId)) {
      S.overlayId = wantOverlay; // asked for in the URL: applied once that map is known
      wantOverlay = "";
      fillMapSelects();
    }
    if (wantMap && S.maps[wantMap] && !S.userPickedMap) {
      setMap(wantMap, true);
      return;
    }
    if (S.userPickedMap && S.maps[S.mapId]) return;
    let best = S.mapId && S.maps[S.mapId] ? S.mapId : ids[0];
    for (const id of ids) if (robotsOn(id) > robotsOn(best)) best = id;
    if (best !== S.mapId) setMap(best, false);
  }
  function setMap(id, byUser) {
    S.mapId = id;
    if (byUser) S.userPickedMap = true;
    if (S.overlayId === id) S.overlayId = "";
    fillMapSelects();
    fit();
  }
  function fillMapSelects() {
    const sel = $("map-select");
    const ov = $("overlay-select");
    const ids = Object.keys(S.maps).sort();
    const label = (id) => `${id} (${S.maps[id].kind === "schematic" ? "floor plan" : "metric"})`;
    const fill = (el, withNone, value) => {
      el.textContent = "";
      if (withNone) el.append(new Option("(none)", ""));
      for (const id of ids) el.append(new Option(label(id), id));
      el.value = value || "";
    };
    fill(sel, false, S.mapId);
    fill(ov, true, S.overlayId);
  }
  $("map-select").addEventListener("change", (e) => setMap(e.target.value, true));
  $("overlay-select").addEventListener("change", (e) => {
    wantOverlay = "";
    S.overlayId = e.target.value === S.mapId ? "" : e.target.value;
    requestDraw();
    sendSelection();
  });

  // ------------------------------------------------------------------ view transform
  function size() {
    return { w: canvas.clientWidth, h: canvas.clientHeight };
  }
  function fit() {
    const m = S.maps[S.mapId];
    const { w, h } = size();
    if (!m || w < 10 || h < 10) { S.view = S.view || { cx: 0, cy: 0, scale: 20 }; return; }
    const [x0, y0, x1, y1] = m.bounds;
    const pad = 24;
    const scale = Math.min((w - 2 * pad) / Math.max(x1 - x0, 0.5), (h - 2 * pad) / Math.max(y1 - y0, 0.5));
    S.view = { cx: (x0 + x1) / 2, cy: (y0 + y1) / 2, scale };
    requestDraw();
  }
  function toScreen(x, y) {
    const v = S.view;
    const { w, h } = size();
    return [(x - v.cx) * v.scale + w / 2, h / 2 - (y - v.cy) * v.scale];
  }
  S.toScreen = toScreen;

  // ------------------------------------------------------------------ drawing
  // One draw per animation frame at most; one carrying new data at most MAX_DRAW_HZ a second
  // (pan and zoom redraw at once: the user is waiting for them).
  let drawPending = false;
  let lastDataDraw = -1e9;
  let lastPanel = -1e9;
  function requestDraw() {
    if (drawPending) return;
    drawPending = true;
    const wait = newData ? lastDataDraw + 1000 / MAX_DRAW_HZ - performance.now() : 0;
    const go = () => requestAnimationFrame(onAnimationFrame);
    if (wait > 1) setTimeout(go, wait); else go();
  }
  function onAnimationFrame() {
    drawPending = false;
    const now = performance.now();
    const hadData = newData;
    newData = false;
    draw();
    if (!hadData) return;
    lastDataDraw = now;
    S.frames += 1;
    S.frameTimes.push(now);
    while (S.frameTimes.length && now - S.frameTimes[0] > 2000) S.frameTimes.shift();
    const n = S.frameTimes.length;
    S.rate = n > 1 ? (1000 * (n - 1)) / (S.frameTimes[n - 1] - S.frameTimes[0]) : 0;
    if (now - lastPanel >= 1000 / PANEL_HZ && S.lastFrame) {
      lastPanel = now;
      updatePanel(S.lastFrame);
    }
    sendSelection();
  }

  function visibleRobots() {
    const out = [];
    for (const r of S.robots.values()) {
      if (r.status === undefined || r.status === null) continue;
      if (r.map !== S.mapId && (!S.overlayId || r.map !== S.overlayId)) continue;
      if (S.hidden.has(r.id)) continue;
      out.push(r);
    }
    return out;
  }

  function drawMap(g, m, colour, width) {
    g.strokeStyle = colour;
    g.lineWidth = width;
    g.lineJoin = "round";
    g.beginPath();
    for (const line of m.polylines) {
      for (let i = 0; i < line.length; i++) {
        const [sx, sy] = toScreen(line[i][0], line[i][1]);
        if (i === 0) g.moveTo(sx, sy); else g.lineTo(sx, sy);
      }
    }
    g.stroke();
  }

  // The maps as drawn at the current view, kept in an offscreen canvas: redrawn only when the
  // maps, the map choice, the view or the canvas size change; otherwise copied in one blit.
  const mapCache = { canvas: document.createElement("canvas"), key: "" };
  function blitMaps(w, h, dpr) {
    const v = S.view;
    const key = [S.mapId, S.overlayId, S.mapsVersion, v.cx, v.cy, v.scale, w, h, dpr].join("|");
    const off = mapCache.canvas;
    if (key !== mapCache.key) {
      mapCache.key = key;
      off.width = Math.round(w * dpr);
      off.height = Math.round(h * dpr);
      const g = off.getContext("2d");
      g.setTransform(dpr, 0, 0, dpr, 0, 0);
      g.fillStyle = "#fcfcfa";
      g.fillRect(0, 0, w, h);
      const p = S.palette;
      if (S.overlayId && S.maps[S.overlayId]) drawMap(g, S.maps[S.overlayId], p.overlay, 1.5);
      const m = S.maps[S.mapId];
      if (m) drawMap(g, m, p.map[m.kind] || "#303030", 1.5);
    }
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.drawImage(off, 0, 0);
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  }

  function arrow(x, y, th, len, head) {
    const [sx, sy] = toScreen(x, y);
    const c = Math.cos(th), s = Math.sin(th);
    const ex = sx + len * c, ey = sy - len * s;
    ctx.moveTo(sx, sy);
    ctx.lineTo(ex, ey);
    ctx.moveTo(ex - head * (c - 0.5 * s), ey + head * (s + 0.5 * c));
    ctx.lineTo(ex, ey);
    ctx.lineTo(ex - head * (c + 0.5 * s), ey + head * (s - 0.5 * c));
  }

  function drawCovariance(r, colour) {
    if (!r.cov) return;
    const [a, b, c] = r.cov;
    const mean = (a + c) / 2, d = Math.sqrt(((a - c) / 2) ** 2 + b * b);
    const l1 = Math.max(mean + d, 0), l2 = Math.max(mean - d, 0);
    const rx = 2 * Math.sqrt(l1) * S.view.scale, ry = 2 * Math.sqrt(l2) * S.view.scale;
    if (!(rx > 3) || rx > 4000) return;
    const ang = 0.5 * Math.atan2(2 * b, a - c);
    const [sx, sy] = toScreen(r.x, r.y);
    ctx.strokeStyle = colour;
    ctx.lineWidth = 1;
    ctx.setLineDash([4, 3]);
    ctx.beginPath();
    ctx.ellipse(sx, sy, rx, Math.max(ry, 1), -ang, 0, 2 * Math.PI);
    ctx.stroke();
    ctx.setLineDash([]);
  }

  // The ranges of a scan message (m, NaN = no return): base64 of little-endian uint16 counts
  // of sc.u metres, 0xFFFF = no return. Unpacked once per scan.
  function ranges(sc) {
    if (sc.ranges) return sc.ranges;
    const bin = atob(sc.d);
    const out = new Float64Array(bin.length >> 1);
    const step = Math.max(1, Math.ceil(out.length / MAX_SCAN_POINTS));
    let points = 0;
    for (let i = 0; i < out.length; i++) {
      const v = bin.charCodeAt(2 * i) | (bin.charCodeAt(2 * i + 1) << 8);
      out[i] = v === 0xffff ? NaN : v * sc.u;
      if (i % step === 0 && v !== 0xffff) points += 1;
    }
    sc.ranges = out;
    sc.points = points; // the points addScan draws (before clipping to the canvas)
    return out;
  }

  // Every shown robot's scan points (at most MAX_SCAN_POINTS each) written as square dots
  // straight into the pixels of a transparent layer, then copied over the canvas in one blit
  // of the rectangle they cover: thousands of points for the price of a few copies (a path of
  // as many rectangles costs the rasteriser several times more).
  const scanLayer = { canvas: document.createElement("canvas"), img: null, px: null, colour: "", rgba: 0 };
  function drawScans(robots, w, h, dpr) {
    const W = Math.round(w * dpr), H = Math.round(h * dpr);
    const L = scanLayer;
    if (!L.img || L.img.width !== W || L.img.height !== H) {
      L.canvas.width = W;
      L.canvas.height = H;
      L.img = new ImageData(W, H);
      L.px = new Uint32Array(L.img.data.buffer);
    }
    if (L.colour !== S.palette.scan) {
      const c = S.palette.scan;
      L.colour = c;
      L.rgba = (0xff000000 | (parseInt(c.slice(5, 7), 16) << 16) |
        (parseInt(c.slice(3, 5), 16) << 8) | parseInt(c.slice(1, 3), 16)) >>> 0;
    }
    const px = L.px, rgba = L.rgba;
    px.fill(0);
    const v = S.view;
    const dot = Math.max(1, Math.round((v.scale > 25 ? 3 : 2) * dpr));
    const k = v.scale * dpr, ox = (w / 2) * dpr - v.cx * k, oy = (h / 2) * dpr + v.cy * k;
    let x0 = W, y0 = H, x1 = -1, y1 = -1;
    for (const r of robots) {
      const sc = r.scan;
      if (!sc || sc.seq !== r.seq) continue;
      const c0 = Math.cos(r.th), s0 = Math.sin(r.th);
      const rs = ranges(sc);
      const step = Math.max(1, Math.ceil(rs.length / MAX_SCAN_POINTS));
      for (let i = 0; i < rs.length; i += step) {
        const d = rs[i];
        if (Number.isNaN(d)) continue;
        const a = sc.a0 + i * sc.da;
        const lx = d * Math.cos(a), ly = d * Math.sin(a);
        const x = r.x + c0 * lx - s0 * ly, y = r.y + s0 * lx + c0 * ly;
        const ix = Math.round(ox + x * k - dot / 2), iy = Math.round(oy - y * k - dot / 2);
        if (ix < 0 || iy < 0 || ix + dot > W || iy + dot > H) continue;
        for (let yy = iy; yy < iy + dot; yy++) px.fill(rgba, yy * W + ix, yy * W + ix + dot);
        if (ix < x0) x0 = ix;
        if (iy < y0) y0 = iy;
        if (ix + dot > x1) x1 = ix + dot;
        if (iy + dot > y1) y1 = iy + dot;
      }
    }
    if (x1 < 0) return;
    L.canvas.getContext("2d").putImageData(L.img, 0, 0, x0, y0, x1 - x0, y1 - y0);
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.drawImage(L.canvas, x0, y0, x1 - x0, y1 - y0, x0, y0, x1 - x0, y1 - y0);
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  }

  function drawCandidates(r) {
    if (!r.cand || !r.cand.length) return;
    const len = Math.max(0.6 * S.view.scale, 14);
    ctx.strokeStyle = S.palette.candidate;
    ctx.fillStyle = S.palette.candidate;
    ctx.font = "11px system-ui, sans-serif";
    r.cand.forEach((c, k) => {
      ctx.globalAlpha = Math.max(0.35, 1 - 0.15 * k);
      ctx.lineWidth = k === 0 ? 2.5 : 1.5;
      ctx.beginPath();
      arrow(c[0], c[1], c[2], len, 6);
      ctx.stroke();
      const [sx, sy] = toScreen(c[0], c[1]);
      ctx.beginPath();
      ctx.arc(sx, sy, 4, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.fillText(`${r.id}#${k + 1}`, sx + 6, sy + 12);
    });
    ctx.globalAlpha = 1;
  }

  function drawPath(r, colour) {
    if (r.path.length < 2) return;
    ctx.strokeStyle = colour;
    ctx.globalAlpha *= 0.45;
    ctx.lineWidth = 2;
    ctx.beginPath();
    const v = S.view;
    const { w, h } = size();
    const n = r.path.length;
    let lx = 0, ly = 0;
    for (let i = 0; i < n; i++) {
      const p = r.path[i];
      const sx = (p[0] - v.cx) * v.scale + w / 2, sy = h / 2 - (p[1] - v.cy) * v.scale;
      if (i === 0) { ctx.moveTo(sx, sy); lx = sx; ly = sy; continue; }
      // a vertex less than 2 px from the last one drawn adds nothing visible
      if (Math.abs(sx - lx) + Math.abs(sy - ly) < 2 && i < n - 1) continue;
      ctx.lineTo(sx, sy);
      lx = sx; ly = sy;
    }
    ctx.stroke();
  }

  function drawBody(r, colour) {
    const [sx, sy] = toScreen(r.x, r.y);
    const rad = Math.max(0.25 * S.view.scale, 6);
    ctx.fillStyle = colour;
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    ctx.arc(sx, sy, rad, 0, 2 * Math.PI);
    ctx.fill();
    ctx.stroke();
    const c = Math.cos(r.th), s = Math.sin(r.th);
    ctx.strokeStyle = "#111111";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(sx + 0.45 * rad * c, sy - 0.45 * rad * s);
    ctx.lineTo(sx + 1.9 * rad * c, sy - 1.9 * rad * s);
    ctx.stroke();
    ctx.fillStyle = "#202020";
    ctx.font = "12px system-ui, sans-serif";
    ctx.fillText(r.id, sx + rad + 3, sy - rad - 2);
    return [sx, sy, rad];
  }

  function drawScaleBar() {
    const { h } = size();
    const target = 120 / S.view.scale;
    const p = 10 ** Math.floor(Math.log10(target));
    const len = [1, 2, 5, 10].map((k) => k * p).filter((v) => v <= target).pop() || p;
    const px = len * S.view.scale;
    ctx.strokeStyle = "#404040";
    ctx.fillStyle = "#404040";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(12, h - 14);
    ctx.lineTo(12 + px, h - 14);
    ctx.moveTo(12, h - 19); ctx.lineTo(12, h - 9);
    ctx.moveTo(12 + px, h - 19); ctx.lineTo(12 + px, h - 9);
    ctx.stroke();
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillText(`${len} m`, 16 + px, h - 10);
  }

  function draw() {
    const dpr = window.devicePixelRatio || 1;
    const { w, h } = size();
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    if (!S.palette) {
      ctx.fillStyle = "#fcfcfa";
      ctx.fillRect(0, 0, w, h);
      return;
    }
    if (!S.view) fit();
    blitMaps(w, h, dpr);
    const robots = visibleRobots();
    for (const r of robots) {
      ctx.globalAlpha = r.stale ? 0.35 : 1;
      drawPath(r, statusColour(r.status));
    }
    ctx.globalAlpha = 1;
    for (const r of robots) drawCandidates(r);
    drawScans(robots, w, h, dpr);
    const drawn = {};
    for (const r of robots) {
      const colour = statusColour(r.status);
      ctx.globalAlpha = r.stale ? 0.35 : 1;
      drawCovariance(r, colour);
      const [px, py, rad] = drawBody(r, colour);
      drawn[r.id] = {
        x: r.x, y: r.y, th: r.th, seq: r.seq, status: r.status, map: r.map,
        colour, px, py, radius: rad, scanPoints: r.scan && r.scan.seq === r.seq
          ? r.scan.points : 0,
        candidates: r.cand ? r.cand.length : 0,
      };
    }
    ctx.globalAlpha = 1;
    S.drawn = drawn;
    drawScaleBar();
  }

  // ------------------------------------------------------------------ side panel
  const rows = new Map();
  const tbody = document.querySelector("#robots tbody");
  function fmt(v, digits) { return v === undefined || v === null ? "–" : Number(v).toFixed(digits); }
  function makeRow(id) {
    const tr = document.createElement("tr");
    const cells = [];
    for (let i = 0; i < 7; i++) { const td = document.createElement("td"); tr.append(td); cells.push(td); }
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = !S.hidden.has(id);
    box.title = "draw this robot";
    box.addEventListener("change", () => {
      if (box.checked) S.hidden.delete(id); else S.hidden.add(id);
      requestDraw();
      sendSelection();
    });
    cells[0].append(box);
    cells[1].textContent = id;
    cells[1].title = "centre on this robot";
    cells[1].addEventListener("click", () => centreOn(id));
    const dot = document.createElement("i");
    dot.className = "dot";
    const label = document.createElement("span");
    cells[2].append(dot, " ", label);
    const row = { tr, cells, box, dot, label };
    rows.set(id, row);
    return row;
  }
  function set(td, text) { if (td.textContent !== text) td.textContent = text; }
  function updatePanel(m) {
    const ids = [...S.robots.keys()].sort();
    const filter = $("filter").value.trim().toLowerCase();
    let order = 0;
    for (const id of ids) {
      const r = S.robots.get(id);
      const row = rows.get(id) || makeRow(id);
      if (tbody.children[order] !== row.tr) tbody.insertBefore(row.tr, tbody.children[order] || null);
      order += 1;
      row.tr.hidden = filter !== "" && !id.toLowerCase().includes(filter);
      const other = r.map !== S.mapId && r.map !== S.overlayId;
      row.tr.className = (other ? "other " : "") + (r.stale ? "stale" : "");
      row.dot.style.background = statusColour(r.status);
      let text = statusLabel(r.status);
      if (r.hyp !== undefined && r.hyp !== null) text += ` (${r.hyp} hyp)`;
      if (r.stale) text += " · stale";
      if (other && r.map) text += ` · ${r.map}`;
      set(row.label, text);
      row.cells[2].title = `${r.method || ""} score ${fmt(r.score, 3)} seq ${r.seq ?? "–"} map ${r.map || "–"}`;
      set(row.cells[3], fmt(r.lat, 1));
      set(row.cells[4], r.explained === undefined ? "–" : `${Math.round(100 * r.explained)} %`);
      set(row.cells[5], fmt(r.ambiguity, 2));
      set(row.cells[6], fmt(r.hz, 1));
      row.box.checked = !S.hidden.has(id);
    }
    for (const [id, row] of rows) if (!S.robots.has(id)) { row.tr.remove(); rows.delete(id); }
    $("rate").textContent = `${S.rate.toFixed(1)} updates/s`;
    const sv = m.service;
    $("service").textContent = sv
      ? `service ${sv.status} · v${sv.version}${sv.instance ? " · " + sv.instance : ""} · ${sv.robots} robots · ${sv.maps} maps · ${sv.processed} scans (${sv.rejected} rejected)`
      : "service: no health answer yet";
    const vw = m.view || {};
    $("footer").textContent = `${S.robots.size} robots · view process CPU ${fmt(vw.cpu, 0)} % · ${m.rejected} samples rejected · frame ${m.n}`;
  }
  $("filter").addEventListener("input", () => { if (S.lastFrame) updatePanel(S.lastFrame); });
  $("all").addEventListener("click", () => { S.hidden.clear(); requestDraw(); sendSelection(); if (S.lastFrame) updatePanel(S.lastFrame); });
  $("none").addEventListener("click", () => {
    for (const id of S.robots.keys()) S.hidden.add(id);
    requestDraw(); sendSelection(); if (S.lastFrame) updatePanel(S.lastFrame);
  });

  function centreOn(id) {
    const r = S.robots.get(id);
    if (!r || r.x === undefined) return;
    if (r.map !== S.mapId && r.map !== S.overlayId && S.maps[r.map]) setMap(r.map, true);
    S.hidden.delete(id);
    S.view.cx = r.x;
    S.view.cy = r.y;
    requestDraw();
    sendSelection();
  }

  // ------------------------------------------------------------------ pan and zoom
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, cx: S.view.cx, cy: S.view.cy };
    canvas.setPointerCapture(e.pointerId);
    canvas.classList.add("dragging");
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    S.view.cx = drag.cx - (e.clientX - drag.x) / S.view.scale;
    S.view.cy = drag.cy + (e.clientY - drag.y) / S.view.scale;
    requestDraw();
  });
  const endDrag = () => { drag = null; canvas.classList.remove("dragging"); };
  canvas.addEventListener("pointerup", endDrag);
  canvas.addEventListener("pointercancel", endDrag);
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const rect = canvas.getBoundingClientRect();
    zoomAt(e.clientX - rect.left, e.clientY - rect.top, Math.exp(-e.deltaY * 0.0015));
  }, { passive: false });
  function zoomAt(mx, my, f) {
    const v = S.view;
    const { w, h } = size();
    const wx = v.cx + (mx - w / 2) / v.scale, wy = v.cy - (my - h / 2) / v.scale;
    v.scale = Math.min(Math.max(v.scale * f, 0.05), 5000);
    v.cx = wx - (mx - w / 2) / v.scale;
    v.cy = wy + (my - h / 2) / v.scale;
    requestDraw();
  }
  canvas.addEventListener("dblclick", fit);
  $("fit").addEventListener("click", fit);
  window.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement) return;
    const { w, h } = size();
    if (e.key === "f") fit();
    else if (e.key === "+" || e.key === "=") zoomAt(w / 2, h / 2, 1.25);
    else if (e.key === "-") zoomAt(w / 2, h / 2, 0.8);
  });
  window.addEventListener("resize", requestDraw);

  // ------------------------------------------------------------------ connection
  let ws = null;
  function sendSelection() {
    if (!ws || ws.readyState !== WebSocket.OPEN) return;
    const ids = visibleRobots().map((r) => r.id).sort();
    const text = JSON.stringify({ type: "select", robots: ids });
    if (text === S.lastSelect) return;
    S.lastSelect = text;
    ws.send(text);
  }
  function connect() {
    const proto = location.protocol === "https:" ? "wss" : "ws";
    ws = new WebSocket(`${proto}://${location.host}/ws`);
    ws.onopen = () => {
      S.connected = true;
      S.lastSelect = null;
      $("conn").textContent = "live";
      $("conn").className = "conn up";
    };
    ws.onmessage = (ev) => {
      let m;
      try { m = JSON.parse(ev.data); } catch (err) { S.errors.push(String(err)); return; }
      if (m.type === "hello") onHello(m);
      else if (m.type === "maps") onMaps(m);
      else if (m.type === "frame") onFrame(m);
    };
    ws.onclose = () => {
      S.connected = false;
      $("conn").textContent = "disconnected: retrying";
      $("conn").className = "conn down";
      setTimeout(connect, 1000);
    };
  }
  window.addEventListener("error", (e) => S.errors.push(String(e.message)));
  connect();
})();
