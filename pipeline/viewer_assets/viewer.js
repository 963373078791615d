// The report's image viewer: linear HDR images (float16) tonemapped here at the chosen exposure,
// flipped in place at the same zoom and pan; FLIP and weight maps in false colour; the relative
// squared error computed here from an image and its set's reference. No network, no libraries.
"use strict";
(function () {
  const payload = JSON.parse(document.getElementById("viewer-payload").textContent);
  const root = document.getElementById("viewer");
  if (!root || !payload.sets.length) return;
  const $ = (sel) => root.querySelector(sel);
  const canvas = $("canvas.stage");
  const ctx = canvas.getContext("2d");
  const ZOOMS = [1 / 16, 1 / 8, 1 / 4, 1 / 2, 1, 2, 4, 8, 16, 32, 64];
  const RELSE_EPS = 0.01, RELSE_LO = -4, RELSE_HI = 1;  // log10 range of the relSE colour scale
  const COLUMNS = payload.columns;
  const state = { set: 0, row: 0, col: "image", exposure: 0, tonemap: "metric", zoom: 1, panX: 0,
                  panY: 0, draws: 0 };
  const decoded = new Map();   // image id -> Promise<{w, h, c, data: Float32Array}>
  const painted = new Map();   // view key -> offscreen canvas
  let drawToken = 0;

  // ---------------------------------------------------------------- decoding
  const HALF = (() => {
    const t = new Float32Array(65536);
    for (let i = 0; i < 65536; i++) {
      const s = i & 0x8000 ? -1 : 1, e = (i >> 10) & 0x1f, m = i & 0x3ff;
      t[i] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * 2 ** (e - 15);
    }
    return t;
  })();

  async function inflate(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  function decode(id) {
    if (!decoded.has(id)) {
      decoded.set(id, (async () => {
        const el = document.getElementById("img-" + id);
        const bin = atob(el.textContent.trim());
        const packed = new Uint8Array(bin.length);
        for (let i = 0; i < bin.length; i++) packed[i] = bin.charCodeAt(i);
        const raw = await inflate(packed);
        const w = +el.dataset.w, h = +el.dataset.h, c = +el.dataset.c, n = w * h * c;
        const data = new Float32Array(n);
        if (el.dataset.dtype === "f16") {  // byte planes: all low bytes, then all high bytes
          for (let i = 0; i < n; i++) data[i] = HALF[raw[i] | (raw[n + i] << 8)];
        } else {
          for (let i = 0; i < n; i++) data[i] = raw[i] / 255;
        }
        return { w, h, c, data };
      })());
    }
    return decoded.get(id);
  }

  // ---------------------------------------------------------------- what is shown
  const sets = () => payload.sets;
  const current = () => sets()[state.set];
  const rowOf = () => current().rows[Math.min(state.row, current().rows.length - 1)];

  function available(row, col) {
    const set = current();
    if (col === "image") return true;
    if (row.kind !== "radiance") return false;
    if (col === "flip") return !!row.flip;
    if (col === "relse") return !!set.reference && row.image !== set.reference;
    return false;
  }

  function view() {
    const row = rowOf();
    const col = available(row, state.col) ? state.col : "image";
    const mode = col === "image" ? row.kind : col;
    return { row, col, mode };
  }

  function viewKey(v) {
    const tone = v.mode === "radiance" ? `${state.exposure}|${state.tonemap}` : "";
    return `${state.set}|${v.row.image}|${v.col}|${tone}`;
  }

  // ---------------------------------------------------------------- colour
  const srgb = (x) => (x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055);
  const TONEMAPS = {
    metric: (x) => Math.pow(x / (1 + x), 1 / 2.2),       // the metrics' tonemap (PSNR, SSIM)
    srgb: (x) => srgb(Math.min(x, 1)),                    // clipped, like an image viewer
  };

  function lut(name, t) {
    const table = payload.colormaps[name];
    const i = Math.max(0, Math.min(255, Math.round(t * 255))) * 3;
    return [table[i], table[i + 1], table[i + 2]];
  }

  async function paint(v) {
    const key = viewKey(v);
    if (painted.has(key)) return painted.get(key);
    const img = await decode(v.col === "flip" ? v.row.flip : v.row.image);
    const out = new ImageData(img.w, img.h);
    const px = out.data, src = img.data, n = img.w * img.h;
    if (v.mode === "radiance") {
      const scale = Math.pow(2, state.exposure), tm = TONEMAPS[state.tonemap];
      for (let i = 0; i < n; i++) {
        for (let k = 0; k < 3; k++) {
          const x = Math.max(0, src[3 * i + k] * scale) || 0;
          px[4 * i + k] = Math.round(255 * tm(x));
        }
        px[4 * i + 3] = 255;
      }
    } else if (v.mode === "relse") {
      const ref = (await decode(current().reference)).data;
      for (let i = 0; i < n; i++) {
        let e = 0;
        for (let k = 0; k < 3; k++) {
          const d = src[3 * i + k] - ref[3 * i + k], r = ref[3 * i + k];
          e += (d * d) / (r * r + RELSE_EPS);
        }
        const t = (Math.log10(e / 3 + 1e-12) - RELSE_LO) / (RELSE_HI - RELSE_LO);
        const [r, g, b] = lut("viridis", Math.max(0, Math.min(1, t)));
        px[4 * i] = r; px[4 * i + 1] = g; px[4 * i + 2] = b; px[4 * i + 3] = 255;
      }
    } else {
      const cmap = v.mode === "flip" ? "magma" : "viridis";
      for (let i = 0; i < n; i++) {
        const [r, g, b] = lut(cmap, src[i]);
        px[4 * i] = r; px[4 * i + 1] = g; px[4 * i + 2] = b; px[4 * i + 3] = 255;
      }
    }
    const off = document.createElement("canvas");
    off.width = img.w; off.height = img.h;
    off.getContext("2d").putImageData(out, 0, 0);
    painted.set(key, off);
    return off;
  }

  // ---------------------------------------------------------------- drawing
  function resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    return dpr;
  }

  async function draw() {
    const token = ++drawToken;
    document.body.dataset.busy = "1";
    const v = view();
    let off;
    try {
      off = await paint(v);
    } catch (err) {
      $(".message").textContent = "cannot show this image: " + err;
      document.body.dataset.busy = "";
      return;
    }
    if (token !== drawToken) return;  // a newer draw started meanwhile
    const dpr = resize();
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.imageSmoothingEnabled = false;
    ctx.fillStyle = "#1a1a1a";
    ctx.fillRect(0, 0, canvas.clientWidth, canvas.clientHeight);
    ctx.drawImage(off, state.panX, state.panY, off.width * state.zoom, off.height * state.zoom);
    updateControls(v);
    state.draws++;
    document.body.dataset.shown = `${state.set}/${v.row.label}/${v.col}`;
    document.body.dataset.draws = String(state.draws);
    document.body.dataset.busy = "";
  }

  function imageSize() {
    const el = document.getElementById("img-" + rowOf().image);
    return [+el.dataset.w, +el.dataset.h];
  }

  function fit() {
    const [w, h] = imageSize();
    const cw = canvas.clientWidth, ch = canvas.clientHeight;
    const z = ZOOMS.filter((z) => w * z <= cw && h * z <= ch).pop() || ZOOMS[0];  // largest that fits
    state.zoom = z;
    state.panX = Math.round((cw - w * z) / 2);
    state.panY = Math.round((ch - h * z) / 2);
  }

  function zoomAt(step, cx, cy) {
    const i = ZOOMS.indexOf(state.zoom);
    const next = ZOOMS[Math.max(0, Math.min(ZOOMS.length - 1, i + step))];
    if (next === state.zoom) return;
    const u = (cx - state.panX) / state.zoom, v = (cy - state.panY) / state.zoom;
    state.panX = Math.round(cx - u * next);
    state.panY = Math.round(cy - v * next);
    state.zoom = next;
    draw();
  }

  // ---------------------------------------------------------------- controls
  function button(label, key, onClick) {
    const b = document.createElement("button");
    b.innerHTML = `<kbd>${key}</kbd> ${label}`;
    b.addEventListener("click", onClick);
    return b;
  }

  function buildButtons() {
    const rows = $(".rows"), cols = $(".cols");
    rows.textContent = "";
    current().rows.forEach((row, i) => rows.appendChild(button(row.label, i + 1, () => pick(i))));
    cols.textContent = "";
    COLUMNS.forEach((c) => cols.appendChild(button(c.label, c.key, () => pickCol(c.id))));
  }

  function updateControls(v) {
    root.querySelectorAll(".rows button").forEach((b, i) => b.classList.toggle("on", i === state.row));
    root.querySelectorAll(".cols button").forEach((b, i) => {
      const c = COLUMNS[i];
      b.classList.toggle("on", c.id === v.col);
      b.disabled = !available(v.row, c.id);
    });
    $(".zoom-label").textContent = state.zoom >= 1 ? `${state.zoom}x` : `1/${1 / state.zoom}x`;
    $(".exposure-label").textContent = (state.exposure >= 0 ? "+" : "") + state.exposure.toFixed(1) + " EV";
    $(".exposure").value = state.exposure;
    const label = v.col === "image" ? v.row.label : `${COLUMNS.find((c) => c.id === v.col).label} of ${v.row.label}`;
    $(".caption").textContent = label;
    $(".legend").innerHTML = legend(v.mode);
    const set = current();
    $(".set-note").textContent = set.note || "";
  }

  function legend(mode) {
    const bar = (name) => {
      const t = payload.colormaps[name], stops = [];
      for (let i = 0; i <= 8; i++) {
        const j = Math.round((i / 8) * 255) * 3;
        stops.push(`rgb(${t[j]},${t[j + 1]},${t[j + 2]}) ${(i / 8) * 100}%`);
      }
      return `<span class="bar" style="background:linear-gradient(90deg,${stops.join(",")})"></span>`;
    };
    if (mode === "flip") return `FLIP 0 ${bar("magma")} 1`;
    if (mode === "relse") return `relative squared error 1e${RELSE_LO} ${bar("viridis")} 1e${RELSE_HI} (log scale, eps ${RELSE_EPS})`;
    if (mode === "weight") return `0 = render kept ${bar("viridis")} 1 = denoiser's output`;
    return "linear radiance, tonemapped here";
  }

  function pick(i) {
    if (i < 0 || i >= current().rows.length) return;
    state.row = i;
    draw();
  }

  function pickCol(id) {
    state.col = id;
    draw();
  }

  function pickSet(i) {
    if (i < 0 || i >= sets().length) return;
    const label = rowOf().label;
    state.set = i;
    const same = current().rows.findIndex((r) => r.label === label);
    state.row = same >= 0 ? same : 0;
    $(".set-select").value = String(i);
    buildButtons();
    draw();
  }

  function setExposure(ev) {
    state.exposure = Math.max(-12, Math.min(12, Math.round(ev * 10) / 10));
    draw();
  }

  async function readout(e) {
    const rect = canvas.getBoundingClientRect();
    const x = Math.floor((e.clientX - rect.left - state.panX) / state.zoom);
    const y = Math.floor((e.clientY - rect.top - state.panY) / state.zoom);
    const v = view();
    const img = await decode(v.col === "flip" ? v.row.flip : v.row.image);
    if (x < 0 || y < 0 || x >= img.w || y >= img.h) { $(".pixel").textContent = ""; return; }
    const i = y * img.w + x, fmt = (a) => Number(a).toPrecision(4);
    let text;
    if (img.c === 3 && v.col !== "relse") {
      text = `R ${fmt(img.data[3 * i])}  G ${fmt(img.data[3 * i + 1])}  B ${fmt(img.data[3 * i + 2])}`;
    } else if (v.col === "relse") {
      const ref = (await decode(current().reference)).data;
      let s = 0;
      for (let k = 0; k < 3; k++) {
        const d = img.data[3 * i + k] - ref[3 * i + k];
        s += (d * d) / (ref[3 * i + k] ** 2 + RELSE_EPS);
      }
      text = `relSE ${fmt(s / 3)}`;
    } else {
      text = `${v.col === "flip" ? "FLIP" : "weight"} ${fmt(img.data[i])}`;
    }
    $(".pixel").textContent = `(${x}, ${y})  ${text}`;
  }

  function bind() {
    const select = $(".set-select");
    if (sets().length > 1) {
      sets().forEach((s, i) => select.add(new Option(s.name, String(i))));
      select.addEventListener("change", () => pickSet(+select.value));
    } else {
      select.parentElement.hidden = true;
    }
    $(".exposure").addEventListener("input", (e) => setExposure(+e.target.value));
    $(".tonemap").addEventListener("change", (e) => { state.tonemap = e.target.value; draw(); });
    $(".zoom-in").addEventListener("click", () => zoomAt(1, canvas.clientWidth / 2, canvas.clientHeight / 2));
    $(".zoom-out").addEventListener("click", () => zoomAt(-1, canvas.clientWidth / 2, canvas.clientHeight / 2));
    $(".zoom-fit").addEventListener("click", () => { fit(); draw(); });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = canvas.getBoundingClientRect();
      zoomAt(e.deltaY < 0 ? 1 : -1, e.clientX - r.left, e.clientY - r.top);
    }, { passive: false });
    let drag = null;
    canvas.addEventListener("pointerdown", (e) => {
      drag = [e.clientX - state.panX, e.clientY - state.panY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", (e) => {
      if (drag) {
        state.panX = Math.round(e.clientX - drag[0]);
        state.panY = Math.round(e.clientY - drag[1]);
        draw();
      }
      readout(e);
    });
    canvas.addEventListener("pointerup", () => { drag = null; });
    window.addEventListener("resize", () => draw());
    document.addEventListener("keydown", (e) => {
      if (e.ctrlKey || e.metaKey || e.altKey || e.target.tagName === "SELECT") return;
      const k = e.key, cw = canvas.clientWidth / 2, ch = canvas.clientHeight / 2;
      const col = COLUMNS.find((c) => c.key === k);
      if (/^[1-9]$/.test(k)) pick(+k - 1);
      else if (col) pickCol(col.id);
      else if (k === "+" || k === "=") zoomAt(1, cw, ch);
      else if (k === "-" || k === "_") zoomAt(-1, cw, ch);
      else if (k === "0") { fit(); draw(); }
      else if (k === "]" || k === "e") setExposure(state.exposure + 0.5);
      else if (k === "[" || k === "E") setExposure(state.exposure - 0.5);
      else if (k === "n" || k === "PageDown") pickSet(state.set + 1);
      else if (k === "p" || k === "PageUp") pickSet(state.set - 1);
      else if (k.startsWith("Arrow")) {
        const step = 32;
        state.panX += k === "ArrowLeft" ? step : k === "ArrowRight" ? -step : 0;
        state.panY += k === "ArrowUp" ? step : k === "ArrowDown" ? -step : 0;
        draw();
      } else return;
      e.preventDefault();
    });
  }

  window.viewer = { state, draw, pick, pickSet, setExposure, zoomAt, fit };
  bind();
  buildButtons();
  fit();
  draw();
})();
