// mapd live view: one EventSource; map tiles drawn into an offscreen canvas (one pixel per cell),
// then that canvas, the robots' outlines, trails and markers drawn at the current zoom and pan.
// Tiles lie on the fleet frame's lattice (mapd/view/tiles.py, the map message in model.py): a map
// that grew keeps its tiles, so the canvas is copied into a bigger one and only new tiles come.
// window.mapdView exposes the state for tests (what is drawn, and where a fleet point lands).
"use strict";
(function () {
  const script = document.currentScript;
  const query = (script && script.dataset.query) || "";
  const canvas = document.getElementById("map");
  const ctx = canvas.getContext("2d");
  const MAP_FORMAT = 2; // the map message's format this page draws (model.py MAP_FORMAT)
  const UNKNOWN_RGB = "#a3a7ad"; // a cell no tile has drawn yet is unknown (tiles.py PALETTE)
  let off = document.createElement("canvas"); // one pixel per cell: replaced when the map grows
  let offctx = off.getContext("2d");
  const $ = (id) => document.getElementById(id);

  const st = {
    geometry: null, // {width, height, resolution, origin: [x, y], tile}
    seq: 0, // newest map message received
    drawnSeq: 0, // newest map message whose tiles are all in the canvas
    version: null,
    pending: 0,
    gen: 0, // bumps when the canvas is recreated: older tile decodes are dropped
    tileSeq: new Map(), // "tx,ty" -> seq of the newest image for that tile
    robots: {},
    status: null,
    view: { scale: 1, x: 0, y: 0, fitted: false, moved: false }, // moved: the user zoomed or panned
    maps: 0,
    loadedAt: Date.now(),
    instance: null, // the serving daemon's run (its hello): another one means a restart
    restarts: 0, // how often the page cleared the state of a daemon that restarted
    retries: 0, // refusals in a row (401, 503): how long to wait before the next try
    // A live daemon sends its status every status_every_s (the hello says): silence past staleAfter
    // is a daemon stopped or a network dropped without a word, which leave the stream open.
    staleAfter: 5, // s
    reconnectAfter: 30, // s: then the stream is dropped and opened again
    stale: false,
    heardAt: Date.now(),
  };
  window.mapdView = st;
  st.cells = () => off; // the canvas of cells (tests read its pixels)

  // ---------------------------------------------------------------- coordinates
  // fleet metres -> map pixel (row 0 at the top) -> CSS pixel on the screen
  function toMap(x, y) {
    const g = st.geometry;
    return [(x - g.origin[0]) / g.resolution, g.height - (y - g.origin[1]) / g.resolution];
  }
  function toScreen(x, y) {
    const [px, py] = toMap(x, y);
    return [st.view.x + px * st.view.scale, st.view.y + py * st.view.scale];
  }
  st.toScreen = toScreen;

  function fit() {
    const g = st.geometry;
    if (!g) return;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    const s = Math.min(w / g.width, h / g.height) * 0.96;
    st.view = { scale: s, x: (w - g.width * s) / 2, y: (h - g.height * s) / 2, fitted: true, moved: false };
    redraw();
  }

  // ---------------------------------------------------------------- drawing
  let frameAsked = false;
  function redraw() {
    if (!frameAsked) {
      frameAsked = true;
      requestAnimationFrame(draw);
    }
  }

  // A robot its link no longer hears is drawn faded, with its pose's age: drawn as live, it looked
  // to be where it was last heard. (Not by the pose's age alone: AMCL publishes only when the robot
  // moves, so a parked robot's pose is old while its link hears it well.)
  let staleNames = "";
  function poseAge(name) {
    const r = st.status && st.status.robots[name];
    return r && typeof r.pose_age_s === "number" ? r.pose_age_s : null;
  }
  function staleRobot(name) {
    const r = st.status && st.status.robots[name];
    if (!r) return false;
    return !r.own && r.present === false;
  }
  st.staleRobot = staleRobot;

  function draw() {
    frameAsked = false;
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#1b1e22";
    ctx.fillRect(0, 0, w, h);
    const g = st.geometry;
    if (!g) return;
    const v = st.view;
    ctx.imageSmoothingEnabled = false; // cells stay crisp squares when zoomed in
    ctx.drawImage(off, v.x, v.y, g.width * v.scale, g.height * v.scale);
    for (const [name, r] of Object.entries(st.robots)) {
      const colour = r.colour || "#888";
      if (r.outline) {
        ctx.beginPath();
        r.outline.forEach(([x, y], i) => {
          const [sx, sy] = toScreen(x, y);
          if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
        });
        ctx.closePath();
        ctx.setLineDash([6, 4]);
        ctx.lineWidth = 2;
        ctx.strokeStyle = colour;
        ctx.stroke();
        ctx.setLineDash([]);
      }
      if (r.trail && r.trail.length > 1) {
        ctx.beginPath();
        r.trail.forEach(([x, y], i) => {
          const [sx, sy] = toScreen(x, y);
          if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
        });
        ctx.lineWidth = 2.5;
        ctx.strokeStyle = colour;
        ctx.globalAlpha = 0.75;
        ctx.stroke();
        ctx.globalAlpha = 1;
      }
      // the robot itself; before any pose is known, its map frame's origin (where it started)
      const at = r.pose || r.frame;
      if (!at) continue;
      const faded = staleRobot(name);
      ctx.globalAlpha = faded ? 0.4 : 1;
      const [sx, sy] = toScreen(at[0], at[1]);
      ctx.beginPath();
      ctx.arc(sx, sy, 9, 0, 2 * Math.PI);
      ctx.fillStyle = colour;
      ctx.fill();
      ctx.lineWidth = 2;
      ctx.strokeStyle = "#ffffff";
      ctx.stroke();
      const yaw = at[2] || 0; // heading: screen y points down
      ctx.beginPath();
      ctx.moveTo(sx, sy);
      ctx.lineTo(sx + 15 * Math.cos(yaw), sy - 15 * Math.sin(yaw));
      ctx.stroke();
      ctx.font = "bold 12px system-ui, sans-serif";
      ctx.lineWidth = 3;
      ctx.strokeStyle = "rgba(0,0,0,.7)";
      const age = poseAge(name);
      const label = !r.pose ? name + " (start)" : faded ? name + (age !== null ? " (" + Math.round(age) + " s ago)" : " (not heard)") : name;
      ctx.strokeText(label, sx + 12, sy - 10);
      ctx.fillStyle = "#fff";
      ctx.fillText(label, sx + 12, sy - 10);
      ctx.globalAlpha = 1;
    }
  }

  // ---------------------------------------------------------------- messages
  // A blank canvas of g's size (every cell unknown), with the old one copied where its cells lie
  // on the lattice now: a map that grew toward -x or +y moves its old cells right or down.
  function newCells(g, keep) {
    const next = document.createElement("canvas");
    next.width = g.width;
    next.height = g.height;
    const nctx = next.getContext("2d");
    nctx.fillStyle = UNKNOWN_RGB;
    nctx.fillRect(0, 0, g.width, g.height);
    if (keep) {
      nctx.imageSmoothingEnabled = false;
      nctx.drawImage(off, keep.lattice[0] - g.lattice[0], keep.lattice[1] - g.lattice[1]);
    }
    off = next;
    offctx = nctx;
  }

  // A page older or newer than its daemon (one upgraded under an open page) cannot draw its tiles:
  // load the page that ships with it, once (a second mismatch says so instead of reloading for ever).
  function wrongFormat(format) {
    const key = "mapd-reloaded-for-format";
    let first = false;
    try {
      first = sessionStorage.getItem(key) !== String(format);
      sessionStorage.setItem(key, String(format));
    } catch (e) {
      first = false; // no storage (a locked-down browser): no way to tell a reload loop, so ask
    }
    if (first) location.reload();
    else setConn("this page is out of date: reload it", "bad");
  }

  function onMap(m) {
    if (m.format !== MAP_FORMAT) return wrongFormat(m.format);
    const g = m.geometry;
    const old = st.geometry;
    const same = old && g.width === old.width && g.height === old.height &&
      g.resolution === old.resolution && g.lattice[0] === old.lattice[0] && g.lattice[1] === old.lattice[1] &&
      g.origin[0] === old.origin[0] && g.origin[1] === old.origin[1];
    if (!same) {
      if (m.full) {
        newCells(g, null);
        st.gen += 1; // tile decodes under way are for a canvas that is gone
        st.tileSeq.clear();
        st.pending = 0;
      } else if (old && g.resolution === old.resolution && g.tile === old.tile) {
        // the map grew (or moved by whole cells) on the same lattice: its old cells stay, and a
        // tile still decoding lands by its lattice place, so nothing under way is dropped
        newCells(g, old);
      } else {
        return; // a delta for a geometry this page does not hold: the full map follows
      }
      if (old && st.view.moved) {
        // keep the same fleet point under the same screen point when the map grows: a point's
        // pixel column (x - ox) / res shifts by -dox / res, but its row height - (y - oy) / res
        // (row 0 is the top) shifts by dheight + doy / res, so the view moves the opposite way
        const dx = (g.origin[0] - old.origin[0]) / g.resolution;
        const dy = (old.height - g.height) + (old.origin[1] - g.origin[1]) / g.resolution;
        st.view.x += dx * st.view.scale;
        st.view.y += dy * st.view.scale;
      }
    }
    st.geometry = g;
    st.seq = m.seq;
    st.version = m.version;
    st.maps += 1;
    if (!st.view.moved) fit();
    const gen = st.gen, seq = m.seq;
    for (const [tx, ty, b64] of m.tiles) {
      const key = tx + "," + ty;
      // the tile's top-left cell on the lattice (an edge tile is clipped to the map it came with)
      const lx = Math.max(tx * g.tile, g.lattice[0]), ly = Math.max(ty * g.tile, g.lattice[1]);
      st.tileSeq.set(key, seq);
      st.pending += 1;
      const img = new Image();
      img.onload = img.onerror = () => {
        if (gen === st.gen) {
          st.pending -= 1;
          if (img.complete && img.naturalWidth && st.tileSeq.get(key) === seq) {
            const now = st.geometry.lattice; // the canvas may have grown since the tile came
            offctx.drawImage(img, lx - now[0], ly - now[1]);
          }
          if (st.pending === 0) st.drawnSeq = st.seq;
          redraw();
        }
      };
      img.src = "data:image/png;base64," + b64;
    }
    if (m.tiles.length === 0) st.drawnSeq = st.pending === 0 ? seq : st.drawnSeq;
    $("mapinfo").textContent = g.width + " × " + g.height + " cells · " + g.resolution + " m";
    redraw();
  }

  const fmt = (v, d = 0) => (v === null || v === undefined ? "–" : Number(v).toFixed(d));
  function kb(v) {
    if (v === null || v === undefined) return "–";
    return v >= 10240 ? (v / 1024).toFixed(0) + " kB" : v >= 1024 ? (v / 1024).toFixed(1) + " kB" : v + " B";
  }
  function cell(tr, text, cls) {
    const td = document.createElement("td");
    td.textContent = text;
    if (cls) td.className = cls;
    tr.appendChild(td);
    return td;
  }

  function renderPanel() {
    const s = st.status;
    if (!s) return;
    $("who").textContent = s.robot + " · fleet " + s.fleet + (s.signed ? "" : " · UNSIGNED");
    const rb = $("robots").tBodies[0];
    rb.textContent = "";
    for (const [name, r] of Object.entries(s.robots)) {
      const tr = rb.insertRow();
      const dot = document.createElement("span");
      dot.className = "dot";
      dot.style.background = (st.robots[name] && st.robots[name].colour) || "#888";
      cell(tr, "").appendChild(dot);
      cell(tr, name + (r.own ? " (this)" : ""));
      const age = poseAge(name);
      cell(tr, age === null ? "–" : fmt(age, 0) + " s", staleRobot(name) ? "warn" : "");
      cell(tr, r.label || "–");
      cell(tr, r.own ? r.keyframes + "k+" + r.deltas + "d" : (r.updates || 0) + " got" + (r.last_kind ? ", last " + r.last_kind : ""));
      cell(tr, r.own ? "last " + kb(r.bytes) : kb(r.bytes));
      const conf = fmt(r.confidence, 2);  // fmt: null or absent shows as a dash
      cell(tr, (r.accepted ? "✓ " : "✗ ") + conf + (r.source ? " " + r.source : ""), r.accepted ? "good" : "warn");
      if (r.reason) {
        const tr2 = rb.insertRow();
        cell(tr2, "");
        const td = cell(tr2, r.reason, "reason");
        td.colSpan = 6;
      }
    }
    const lb = $("links").tBodies[0];
    lb.textContent = "";
    for (const l of s.links) {
      const tr = lb.insertRow();
      cell(tr, l.name);
      cell(tr, fmt(l.tx_bps));
      cell(tr, l.use === null ? "–" : (100 * l.use).toFixed(0) + "% of " + fmt(l.budget_bps), l.use > 0.8 ? "warn" : "");
      cell(tr, l.rtt_ms === null ? "–" : fmt(l.rtt_ms) + " ms");
      cell(tr, fmt(l.resends));
      cell(tr, l.last_heard_s === null ? "–" : fmt(l.last_heard_s, 1) + " s", l.last_heard_s > 30 ? "warn" : "");
    }
  }

  // A new daemon (restarted) has its own maps: what the page holds is the old one's, so it goes
  // (the new daemon's state follows the hello at once, if it has any yet).
  function onHello(m) {
    if (st.instance !== null && m.instance !== st.instance) {
      st.geometry = null;
      st.seq = st.drawnSeq = st.pending = 0;
      st.version = null;
      st.gen += 1; // tile decodes still under way belong to the old map
      st.tileSeq.clear();
      st.robots = {};
      st.status = null;
      st.view.moved = false; // the new map is fitted to the window
      st.restarts += 1;
      for (const id of ["mapinfo", "who"]) $(id).textContent = "";
      for (const id of ["robots", "links"]) $(id).tBodies[0].textContent = "";
      redraw();
    }
    st.instance = m.instance;
    if (m.status_every_s) st.staleAfter = Math.max(5, 3 * m.status_every_s);
    if (m.keepalive_s) st.reconnectAfter = Math.max(st.staleAfter + 5, 2 * m.keepalive_s);
  }

  // ---------------------------------------------------------------- the stream
  function setConn(text, cls) {
    $("conn").textContent = text;
    $("conn").className = cls;
  }

  let countdown = 0;
  // An answer other than 200 (503: the viewer or connection cap; 401: the token changed) makes the
  // browser close the EventSource for good; only a broken stream is retried by the browser. So try
  // again after 5, 10, then 20 s, each up to half as long again at random: pages refused together
  // by a full daemon do not all come back in the same second. (EventSource does not show the 503's
  // Retry-After, 10 s.)
  // ``why``: what the page says while it waits ("disconnected", or that the token was refused).
  function retryLater(why) {
    const base = [5, 10, 20][Math.min(st.retries, 2)];
    st.retries += 1;
    let left = Math.round(base + Math.random() * base / 2);
    setConn(why + ", retrying in " + left + " s", "bad");
    clearInterval(countdown);
    countdown = setInterval(() => {
      left -= 1;
      if (left > 0) {
        setConn(why + ", retrying in " + left + " s", "bad");
      } else {
        clearInterval(countdown);
        setConn("connecting", "bad");
        connect();
      }
    }, 1000);
  }

  // Every event says the daemon is there; a stream open and silent for long is not live.
  let stream = null;
  function heard() {
    st.heardAt = Date.now();
    if (st.stale) { st.stale = false; setConn("live", "ok"); }
  }
  setInterval(() => {
    if (!stream || stream.readyState !== EventSource.OPEN) return;
    const quiet = (Date.now() - st.heardAt) / 1000;
    if (quiet > st.reconnectAfter) {
      stream.close(); // half-open (the network dropped): a new stream finds out
      st.stale = false;
      setConn("no update for " + Math.round(quiet) + " s; reconnecting", "bad");
      connect();
    } else if (quiet > st.staleAfter) {
      st.stale = true;
      setConn("no update for " + Math.round(quiet) + " s (daemon stopped, or the network?)", "bad");
    }
  }, 1000);

  function connect() {
    const es = new EventSource("events" + query);
    stream = es;
    es.onopen = () => { st.retries = 0; st.stale = false; st.heardAt = Date.now(); setConn("live", "ok"); };
    es.onerror = () => {
      if (es.readyState === EventSource.CLOSED) {
        es.close();
        // EventSource does not show the refusal's status. A 401 (the daemon's token was rotated by
        // a reload) needs a person with the new link, not patience: ask once, with a HEAD of an
        // asset (every route checks the token; assets are not held to the viewer cap), and say so.
        fetch("static/view.css" + query, { method: "HEAD", cache: "no-store" })
          .then((r) => (r.status === 401 ? "token refused (rotated?)" : "disconnected"),
                () => "disconnected")
          .then(retryLater);
      } else {
        setConn("reconnecting", "bad"); // the stream broke: the browser tries again by itself
      }
    };
    es.addEventListener("hello", (e) => { heard(); onHello(JSON.parse(e.data)); });
    es.addEventListener("map", (e) => { heard(); onMap(JSON.parse(e.data)); });
    es.addEventListener("robots", (e) => { heard(); st.robots = JSON.parse(e.data).robots; redraw(); renderPanel(); });
    es.addEventListener("status", (e) => {
      heard();
      st.status = JSON.parse(e.data);
      const was = staleNames;
      staleNames = Object.keys(st.status.robots).filter(staleRobot).sort().join(",");
      if (staleNames !== was || staleNames) redraw(); // markers faded or back; faded ones' ages
      renderPanel();
    });
  }

  // ---------------------------------------------------------------- zoom and pan (mouse, touch, pen)
  function zoomAt(cx, cy, factor) {
    const v = st.view;
    const s = Math.min(64, Math.max(0.02, v.scale * factor));
    const k = s / v.scale;
    v.moved = true;
    v.x = cx - (cx - v.x) * k;
    v.y = cy - (cy - v.y) * k;
    v.scale = s;
    redraw();
  }
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const r = canvas.getBoundingClientRect();
    zoomAt(e.clientX - r.left, e.clientY - r.top, Math.exp(-e.deltaY * 0.0015));
  }, { passive: false });
  const pointers = new Map();
  let pinch = null;
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, [e.clientX, e.clientY]);
    canvas.classList.add("dragging");
  });
  canvas.addEventListener("pointermove", (e) => {
    const prev = pointers.get(e.pointerId);
    if (!prev) return;
    pointers.set(e.pointerId, [e.clientX, e.clientY]);
    st.view.moved = true;
    if (pointers.size === 1) {
      st.view.x += e.clientX - prev[0];
      st.view.y += e.clientY - prev[1];
      redraw();
    } else if (pointers.size === 2) {
      const [a, b] = [...pointers.values()];
      const d = Math.hypot(a[0] - b[0], a[1] - b[1]);
      const r = canvas.getBoundingClientRect();
      const mx = (a[0] + b[0]) / 2 - r.left, my = (a[1] + b[1]) / 2 - r.top;
      if (pinch) {
        st.view.x += mx - pinch.mx;
        st.view.y += my - pinch.my;
        zoomAt(mx, my, d / pinch.d);
      }
      pinch = { d, mx, my };
    }
  });
  const up = (e) => {
    pointers.delete(e.pointerId);
    pinch = null;
    if (pointers.size === 0) canvas.classList.remove("dragging");
  };
  canvas.addEventListener("pointerup", up);
  canvas.addEventListener("pointercancel", up);
  canvas.addEventListener("dblclick", fit);
  $("fit").addEventListener("click", fit);
  $("toggle").addEventListener("click", () => { $("panel").classList.toggle("hidden"); refit(); });
  // until the user moves the map, it stays fitted to the window (a phone turned, the panel hidden)
  const refit = () => (st.view.moved ? redraw() : fit());
  window.addEventListener("resize", refit);
  if (window.ResizeObserver) new ResizeObserver(refit).observe(canvas);

  connect();
  redraw();
})();
