// ControlGS viewer page: sends the state on every control change, shows the newest answer.
// A new request aborts the previous fetch; the server drops superseded work (409).
"use strict";

const $ = (id) => document.getElementById(id);
const ROWS = [["rendered", "rendered frame"], ["eye", "eye image"], ["diff", "|eye − GT|"]];
const METRICS = {psnr: [" dB", 3, true], ssim: ["", 4, true], flip: ["", 4, false], cvvdp: [" JOD", 3, true]};
let info = null;
let controller = null;
let gaze = null;
window.viewer = {generation: 0, last: null, latencyMs: null, extra: null};

function setStatus(text, kind) {
  const s = $("status");
  s.textContent = text;
  s.className = kind || "";
}

function currentState() {
  return {
    view: Number($("view").value), azimuth: Number($("azimuth").value), elevation: Number($("elevation").value),
    downsample: Number($("downsample").value), power_saving: Number($("power_saving").value),
    optics: $("optics").value, stages: info.stages.filter((s) => $("stage-" + s).checked), gaze: gaze,
  };
}

function png(b64) { return b64 ? "data:image/png;base64," + b64 : ""; }

function cell(id, overlay) {
  const div = document.createElement("div");
  div.className = "cell";
  const img = document.createElement("img");
  img.id = id;
  img.alt = id;
  img.addEventListener("click", (e) => setGaze(e, img));
  div.appendChild(img);
  if (overlay) {
    const o = document.createElement("img");
    o.id = id + "-overlay";
    o.className = "overlay";
    o.alt = "";
    div.appendChild(o);
  }
  const mark = document.createElement("div");
  mark.className = "gaze";
  mark.hidden = true;
  div.appendChild(mark);
  return div;
}

function buildGrid() {
  const grid = $("grid");
  const head = grid.insertRow();
  head.appendChild(document.createElement("th"));
  for (const label of ["Ground truth", ...info.methods.map((m) => m.label)]) {
    const th = document.createElement("th");
    th.textContent = label;
    head.appendChild(th);
  }
  for (const [row, label] of ROWS) {
    const tr = grid.insertRow();
    const th = document.createElement("th");
    th.className = "row";
    th.textContent = row === "diff" ? `${label} × ${info.diff_gain}` : label;
    tr.appendChild(th);
    const gtCell = tr.insertCell();
    if (row === "eye") gtCell.appendChild(cell("img-gt", false));
    for (const m of info.methods) tr.insertCell().appendChild(cell(`img-${m.name}-${row}`, row === "rendered"));
  }
  const tr = grid.insertRow();
  const th = document.createElement("th");
  th.className = "row";
  th.textContent = "vs GT";
  tr.appendChild(th);
  tr.insertCell();
  for (const m of info.methods) {
    const td = tr.insertCell();
    td.className = "metrics";
    td.id = `metrics-${m.name}`;
    for (const k of ["psnr", "ssim", ...info.extra_metrics]) {
      const div = document.createElement("div");
      div.innerHTML = `${k.toUpperCase()} <span id="metric-${m.name}-${k}">–</span>`;
      td.appendChild(div);
    }
    const bands = document.createElement("div");
    bands.className = "bands";
    bands.id = `bands-${m.name}`;
    td.appendChild(bands);
  }
}

function setGaze(event, img) {
  const r = img.getBoundingClientRect();
  gaze = [2 * (event.clientX - r.left) / r.width - 1, 2 * (event.clientY - r.top) / r.height - 1]
    .map((v) => Math.max(-1, Math.min(1, Math.round(v * 1000) / 1000)));
  showGaze();
  request();
}

function showGaze() {
  $("gaze-out").textContent = gaze ? `(${gaze[0].toFixed(2)}, ${gaze[1].toFixed(2)})` : "none";
  for (const mark of document.querySelectorAll(".gaze")) {
    mark.hidden = !gaze;
    if (gaze) {
      mark.style.left = `${50 * (gaze[0] + 1)}%`;
      mark.style.top = `${50 * (gaze[1] + 1)}%`;
    }
  }
}

function formatMetric(k, v) {
  const [unit, digits] = METRICS[k] || ["", 4];
  return v === null || v === undefined || !isFinite(v) ? "–" : v.toFixed(digits) + unit;
}

function setMetric(method, k, v) {
  const el = $(`metric-${method}-${k}`);
  if (!el) return;
  el.textContent = formatMetric(k, v);
  el.dataset.value = v === null || v === undefined ? "" : String(v);
}

function markBest(methods, k) {
  const higher = (METRICS[k] || [0, 0, true])[2];
  const vals = methods.map((m) => Number($(`metric-${m}-${k}`).dataset.value));
  const ok = vals.filter((v) => isFinite(v));
  const best = ok.length ? (higher ? Math.max(...ok) : Math.min(...ok)) : NaN;
  methods.forEach((m, i) => $(`metric-${m}-${k}`).classList.toggle("best", vals[i] === best));
}

function show(data, latency) {
  $("img-gt").src = png(data.gt);
  $("img-gt").parentElement.style.visibility = data.gt ? "visible" : "hidden";
  const strengths = [];
  for (const m of data.methods) {
    $(`img-${m.name}-rendered`).src = png(m.rendered);
    $(`img-${m.name}-rendered`).title = `${m.rendered_size[0]}×${m.rendered_size[1]} px`;
    $(`img-${m.name}-rendered-overlay`).src = png(m.overlay);
    $(`img-${m.name}-rendered-overlay`).hidden = !m.overlay;
    $(`img-${m.name}-eye`).src = png(m.eye);
    $(`img-${m.name}-diff`).src = png(m.diff);
    $(`img-${m.name}-diff`).parentElement.style.visibility = m.diff ? "visible" : "hidden";
    for (const k of ["psnr", "ssim"]) setMetric(m.name, k, m.metrics ? m.metrics[k] : null);
    $(`bands-${m.name}`).innerHTML = m.bands ? info.bands.map(([b, lo, hi]) => {
      const p = m.bands[`psnr_${b}`], s = m.bands[`ssim_${b}`];
      const range = hi === null ? `≥${lo}°` : `${lo}–${hi}°`;
      return `<div title="PSNR / SSIM over the pixels ${range} from the gaze">${b} ` +
        `${p === null ? "–" : p.toFixed(2)} / ${s === null ? "–" : s.toFixed(3)}</div>`;
    }).join("") : "";
    for (const k of info.extra_metrics) {
      const el = $(`metric-${m.name}-${k}`);
      el.textContent = m.metrics ? "…" : "–";
      el.dataset.value = "";
    }
    const parts = Object.entries(m.strengths).map(([k, v]) => typeof v === "number"
      ? `λ<sub>${k}</sub> ${v.toFixed(3)}`
      : `λ<sub>${k}</sub> mean ${v.mean.toFixed(3)} (${v.min.toFixed(2)}–${v.max.toFixed(2)})`);
    if (parts.length) strengths.push(`<div><b>${m.label}</b>: ${parts.join(", ")}</div>`);
  }
  const names = data.methods.map((m) => m.name);
  if (data.has_truth) for (const k of ["psnr", "ssim"]) markBest(names, k);
  $("strengths").innerHTML = strengths.join("");
  const ran = data.methods.length ? data.methods[0].stages_run.join(" → ") || "none" : "";
  $("legend").textContent = `${data.size[0]}×${data.size[1]} px; stages run: ${ran}; optics ${data.state.optics}.` +
    (data.has_truth ? "" : " This orbit view has no ground truth: the SS-backbone render is the display's power " +
      "reference and no metrics are shown.");
  window.viewer.generation = data.generation;
  window.viewer.last = data.state;
  window.viewer.latencyMs = latency;
  const s = $("status");
  s.dataset.generation = String(data.generation);
  setStatus(`updated in ${latency.toFixed(0)} ms (server ${data.server_ms.toFixed(0)} ms, ${info.device})`, "");
  s.dataset.generation = String(data.generation);
}

async function post(path, body, signal) {
  const resp = await fetch(path, {method: "POST", headers: {"Content-Type": "application/json"},
    body: JSON.stringify(body), signal});
  return [resp.status, await resp.json()];
}

async function request() {
  if (controller) controller.abort();
  const mine = new AbortController();
  controller = mine;
  const sent = performance.now();
  setStatus("rendering…", "busy");
  try {
    const [status, data] = await post("/api/render", currentState(), mine.signal);
    if (status === 409) return;  // superseded: the newer request answers
    if (status !== 200) { setStatus(data.error, "error"); return; }
    show(data, performance.now() - sent);
    if (!info.extra_metrics.length || !data.has_truth) return;
    const [s2, extra] = await post("/api/extra", {generation: data.generation}, mine.signal);
    if (s2 !== 200) return;
    const names = Object.keys(extra.metrics);
    for (const m of names) for (const [k, v] of Object.entries(extra.metrics[m])) setMetric(m, k, v);
    for (const k of info.extra_metrics) markBest(names, k);
    window.viewer.extra = extra.generation;
  } catch (e) {
    if (e.name !== "AbortError") setStatus("no answer from the server: " + e, "error");
  }
}

function outputs() {
  $("downsample-out").textContent = Number($("downsample").value).toFixed(2);
  $("power_saving-out").textContent = Number($("power_saving").value).toFixed(2);
  $("azimuth-out").textContent = $("azimuth").value;
  $("elevation-out").textContent = $("elevation").value;
}

async function init() {
  info = await (await fetch("/api/info")).json();
  $("scene").textContent = `${info.name} · ${info.device}`;
  info.views.forEach((v, i) => $("view").add(new Option(v, String(i))));
  info.optics_modes.forEach((m) => $("optics").add(new Option(m, m)));
  for (const s of info.stages) {
    const label = document.createElement("label");
    label.innerHTML = `<input type="checkbox" id="stage-${s}"> ${s}`;
    $("stages").appendChild(label);
  }
  const d = info.defaults;
  for (const k of ["downsample", "power_saving", "azimuth", "elevation"]) {
    $(k).min = String(info.ranges[k][0]);
    $(k).max = String(info.ranges[k][1]);
    $(k).value = String(d[k]);
  }
  $("optics").value = d.optics;
  for (const s of info.stages) $("stage-" + s).checked = d.stages.includes(s);
  buildGrid();
  outputs();
  for (const k of ["downsample", "power_saving", "azimuth", "elevation"]) {
    $(k).addEventListener("input", () => { outputs(); request(); });
  }
  for (const el of [$("view"), $("optics"), ...info.stages.map((s) => $("stage-" + s))]) {
    el.addEventListener("change", request);
  }
  $("reset-orbit").addEventListener("click", () => { $("azimuth").value = "0"; $("elevation").value = "0"; outputs(); request(); });
  $("clear-gaze").addEventListener("click", () => { gaze = null; showGaze(); request(); });
  $("show-overlay").addEventListener("change", () => document.body.classList.toggle("no-overlay", !$("show-overlay").checked));
  request();
}

init().catch((e) => setStatus("could not start: " + e, "error"));
