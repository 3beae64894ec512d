// posemetry operator console: reads the API with the operator's key and draws what it finds.
//
// The key is typed once and kept in this tab's sessionStorage (gone when the tab closes); it is sent only as an
// Authorization: Bearer header by fetch, never in a URL, a cookie or a form submission. Every string from the API
// is shown with textContent or as an SVG text node, never parsed as HTML. Pictures are fetched with the key and
// shown from blob: URLs, so an <img src> never needs one.
"use strict";

(() => {
  const KEY_STORAGE = "posemetry.key";
  const SVG = "http://www.w3.org/2000/svg";
  const $ = (id) => document.getElementById(id);

  let caller = null;
  let selected = null;
  let timer = null;
  const shown = new Map(); // img id -> {version, url} of the blob it shows

  class ApiError extends Error {
    constructor(status, detail) {
      super(detail);
      this.status = status;
    }
  }

  async function api(path, as = "json") {
    const key = sessionStorage.getItem(KEY_STORAGE);
    const response = await fetch(path, {
      headers: { Authorization: `Bearer ${key}` },
      credentials: "omit",
      cache: "no-store",
    });
    if (!response.ok) {
      let detail = `${response.status} ${response.statusText}`;
      try {
        const problem = await response.json();
        detail = problem.detail || problem.title || detail;
      } catch (_) {
        // not a problem document: keep the status line
      }
      throw new ApiError(response.status, detail);
    }
    return as === "blob" ? response.blob() : response.json();
  }

  const cameraPath = (id) => `/v1/cameras/${encodeURIComponent(id)}`;

  function element(tag, text, className) {
    const node = document.createElement(tag);
    if (text !== undefined && text !== null) node.textContent = String(text);
    if (className) node.className = className;
    return node;
  }

  function svg(tag, attributes, text) {
    const node = document.createElementNS(SVG, tag);
    for (const [name, value] of Object.entries(attributes || {})) node.setAttribute(name, String(value));
    if (text !== undefined) node.textContent = String(text);
    return node;
  }

  function fixed(value, digits) {
    return value === null || value === undefined ? "–" : Number(value).toFixed(digits);
  }

  function time(iso) {
    return new Date(iso).toISOString().replace("T", " ").slice(0, 19) + " UTC";
  }

  const tiltDeg = (normal) => (normal ? (Math.asin(Math.max(-1, Math.min(1, -normal[2]))) * 180) / Math.PI : null);

  // ------------------------------------------------------------------------------------------------ signing in

  function showError(message) {
    const error = $("error");
    error.textContent = message;
    error.hidden = !message;
  }

  async function start() {
    try {
      caller = await api("/v1/keys/current");
    } catch (exc) {
      if (exc instanceof ApiError && exc.status === 401) signOut(`The API refused this key: ${exc.message}`);
      else showError(`The API could not be read (${exc.message}); try again.`);
      return;
    }
    showError("");
    $("login").hidden = true;
    $("dashboard").hidden = false;
    $("sign-out").hidden = false;
    const scope = caller.cameras ? `cameras ${caller.cameras.join(", ")}` : "all cameras";
    $("who").textContent = `key “${caller.name}” · ${caller.admin ? "admin" : "not admin"} · ${scope}`;
    await refresh();
    clearInterval(timer);
    timer = setInterval(refresh, 1000 * Number(document.body.dataset.refreshS || 15));
  }

  function signOut(message) {
    sessionStorage.removeItem(KEY_STORAGE);
    clearInterval(timer);
    caller = null;
    selected = null;
    // Nothing the key could read stays on the page for the next person at this screen.
    for (const { url } of shown.values()) URL.revokeObjectURL(url);
    shown.clear();
    for (const img of document.querySelectorAll("img.picture")) {
      img.removeAttribute("src");
      img.hidden = true;
    }
    for (const id of ["history", "violations"]) $(id).replaceChildren();
    for (const body of document.querySelectorAll("#dashboard tbody")) body.replaceChildren();
    for (const id of ["history-camera", "frame-caption", "violations-total"]) $(id).textContent = "";
    $("dashboard").hidden = true;
    $("sign-out").hidden = true;
    $("login").hidden = false;
    $("who").textContent = "";
    $("refreshed").textContent = "";
    showError(message || "");
  }

  // ------------------------------------------------------------------------------------------------ refreshing

  // One refresh at a time: a click during one asks for another right after it.
  let refreshing = false;
  let again = false;

  async function refresh() {
    if (refreshing) {
      again = true;
      return;
    }
    refreshing = true;
    try {
      await refreshOnce();
    } finally {
      refreshing = false;
    }
    if (again && caller) {
      again = false;
      await refresh();
    }
  }

  async function refreshOnce() {
    try {
      const cameras = (await api("/v1/cameras?limit=100")).items;
      const statuses = await Promise.all(cameras.map((c) => api(`${cameraPath(c.id)}/calibration`)));
      if (!caller) return; // the key was forgotten meanwhile
      if (!cameras.some((c) => c.id === selected)) selected = cameras.length ? cameras[0].id : null;
      drawCameras(cameras, statuses);
      $("camera").hidden = selected === null;
      const work = [drawWebhooks()];
      if (selected !== null) work.push(drawCamera(selected));
      await Promise.all(work);
      $("refreshed").textContent = `updated ${new Date().toISOString().slice(11, 19)} UTC`;
      $("refreshed").classList.remove("error");
    } catch (exc) {
      if (exc instanceof ApiError && exc.status === 401) {
        signOut(`The API no longer accepts this key: ${exc.message}`);
        return;
      }
      $("refreshed").textContent = `refresh failed: ${exc.message}`;
      $("refreshed").classList.add("error");
    }
  }

  // --------------------------------------------------------------------------------------------------- cameras

  // How sure the current calibration is, from the 1-sigma of its focal length (the least certain of its numbers).
  function quality(status) {
    if (status.status !== "calibrated" || !status.fx_px) return { text: "–", grade: "none" };
    const u = status.uncertainty || {};
    const relative = u.fx_std_px ? u.fx_std_px / status.fx_px : null;
    const grade = relative === null ? "unknown" : relative < 0.03 ? "good" : relative < 0.1 ? "fair" : "poor";
    const parts = [relative === null ? "no sigma" : grade];
    if (relative !== null) parts.push(`f ±${(100 * relative).toFixed(1)}%`);
    if (status.inliers && status.people_used) parts.push(`${Math.round((100 * status.inliers) / status.people_used)}% inliers`);
    return { text: parts.join(" · "), grade };
  }

  // "uncalibrated: camera moved 2026-11-25 00:40:02 UTC · epoch 2": why a camera that had a calibration has none.
  function statusText(status) {
    const reasons = { camera_moved: "camera moved", reset: "calibration reset", image_size_changed: "image size changed" };
    let text = status.status;
    if (status.reason) {
      text += `: ${reasons[status.reason] || status.reason}`;
      if (status.reason === "camera_moved" && status.moved_at) text += ` ${time(status.moved_at)}`;
    }
    if (status.epoch > 1) text += ` · epoch ${status.epoch}`;
    if (status.last_failure) text += ` (last solve failed: ${status.last_failure})`;
    return text;
  }

  function drawCameras(cameras, statuses) {
    const body = $("cameras").querySelector("tbody");
    body.replaceChildren();
    cameras.forEach((camera, k) => {
      const status = statuses[k];
      const row = element("tr");
      row.dataset.camera = camera.id;
      if (camera.id === selected) row.classList.add("selected");
      const pick = element("button", camera.id, "link");
      pick.type = "button";
      pick.addEventListener("click", () => {
        selected = camera.id;
        refresh();
      });
      const name = element("td");
      name.append(pick);
      const q = quality(status);
      row.append(
        name,
        element("td", statusText(status), `status ${status.status}`),
        element("td", q.text, `grade ${q.grade}`),
        element("td", status.status === "uncalibrated" ? status.people_needed : `${status.people_needed} to the next solve`),
        element("td", status.fx_px ? `${fixed(status.fx_px, 0)} px` : "–"),
        element("td", status.rho_m ? `${fixed(status.rho_m, 2)} m` : "–"),
      );
      body.append(row);
    });
    $("no-cameras").hidden = cameras.length > 0;
  }

  async function drawCamera(id) {
    const path = cameraPath(id);
    const [history, frames, violations] = await Promise.all([
      api(`${path}/calibration/history?limit=50`),
      api(`${path}/frames?status=done&limit=1`),
      api(`${path}/violations?bucket=hour`),
    ]);
    if (id !== selected) return; // another camera was picked meanwhile
    $("history-camera").textContent = id;
    drawHistory(history.items);
    await Promise.all([drawFrame(frames.items[0]), drawViolations(id, violations)]);
  }

  // ----------------------------------------------------------------------------------------------- history charts

  function drawHistory(items) {
    const solves = items.filter((v) => v.status === "ok").reverse(); // oldest first
    const box = $("history");
    box.replaceChildren();
    if (!solves.length) {
      box.append(element("p", "No calibration yet.", "muted"));
      return;
    }
    const series = (value, sigma) => solves.map((v) => ({ x: v.version, y: value(v), s: sigma(v), epoch: v.epoch }));
    const u = (v) => v.uncertainty || {};
    box.append(
      chart("focal length f", "px", 0, series((v) => v.fx_px, (v) => u(v).fx_std_px)),
      chart("tilt below horizon", "°", 1, series((v) => tiltDeg(v.normal), (v) => u(v).normal_std_deg)),
      chart("camera height", "m", 2, series((v) => v.rho_m, (v) => u(v).rho_std_m)),
      chart("evidence (people)", "", 0, series((v) => v.evidence_count, () => null)),
    );
  }

  // A small line chart of one calibration number by version, its ±1 sigma as a band.
  function chart(title, unit, digits, points) {
    const W = 300, H = 110, left = 8, right = 8, top = 26, bottom = 18;
    const valid = points.filter((p) => p.y !== null && p.y !== undefined && Number.isFinite(p.y));
    const figure = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "chart", role: "img" });
    const last = valid[valid.length - 1];
    const sigma = last && last.s ? ` ± ${fixed(last.s, digits)}` : "";
    figure.append(svg("title", {}, `${title} by calibration version`));
    figure.append(svg("text", { x: left, y: 14, class: "chart-title" }, title));
    figure.append(
      svg("text", { x: W - right, y: 14, class: "chart-value", "text-anchor": "end" },
        last ? `${fixed(last.y, digits)}${sigma} ${unit}`.trim() : "–"),
    );
    if (!valid.length) return figure;
    const lows = valid.map((p) => p.y - (p.s || 0)), highs = valid.map((p) => p.y + (p.s || 0));
    let y0 = Math.min(...lows), y1 = Math.max(...highs);
    if (y1 - y0 < 1e-9) {
      const pad = Math.abs(y0) * 0.05 || 1;
      y0 -= pad;
      y1 += pad;
    }
    const x0 = valid[0].x, x1 = valid[valid.length - 1].x;
    const px = (x) => (x1 === x0 ? (left + W - right) / 2 : left + ((x - x0) / (x1 - x0)) * (W - left - right));
    const py = (y) => top + (1 - (y - y0) / (y1 - y0)) * (H - top - bottom);
    const coords = (list) => list.map(([x, y]) => `${px(x).toFixed(1)},${py(y).toFixed(1)}`).join(" ");
    // Each epoch (a new one when the camera moved, or was reset) its own line and band, after a dashed mark.
    const runs = [];
    valid.forEach((p, k) => {
      if (k === 0 || p.epoch !== valid[k - 1].epoch) {
        runs.push([]);
        if (k > 0) {
          const x = ((px(valid[k - 1].x) + px(p.x)) / 2).toFixed(1);
          figure.append(svg("line", { x1: x, x2: x, y1: top - 4, y2: H - bottom, class: "epoch" }));
          figure.append(svg("text", { x, y: H - 4, class: "axis", "text-anchor": "middle" }, `epoch ${p.epoch}`));
        }
      }
      runs[runs.length - 1].push(p);
    });
    for (const run of runs) {
      if (run.some((p) => p.s)) {
        const upper = run.map((p) => [p.x, p.y + (p.s || 0)]);
        const lower = run.map((p) => [p.x, p.y - (p.s || 0)]).reverse();
        figure.append(svg("polygon", { points: coords([...upper, ...lower]), class: "band" }));
      }
      figure.append(svg("polyline", { points: coords(run.map((p) => [p.x, p.y])), class: "line" }));
    }
    for (const p of valid) figure.append(svg("circle", { cx: px(p.x).toFixed(1), cy: py(p.y).toFixed(1), r: 2.5, class: "dot" }));
    figure.append(svg("text", { x: left, y: H - 4, class: "axis" }, `v${x0}`));
    if (x1 !== x0) figure.append(svg("text", { x: W - right, y: H - 4, class: "axis", "text-anchor": "end" }, `v${x1}`));
    return figure;
  }

  // ------------------------------------------------------------------------------------------------- pictures

  // `version` names what the picture shows: it is fetched again only when that changes.
  async function showPicture(id, source, version = source) {
    const img = $(id);
    if (!source) {
      img.hidden = true;
      return;
    }
    const current = shown.get(id);
    if (current && current.version === version) return;
    const url = URL.createObjectURL(await api(source, "blob"));
    if (current) URL.revokeObjectURL(current.url);
    shown.set(id, { version, url });
    img.src = url;
    img.hidden = false;
  }

  async function drawFrame(frame) {
    $("no-frame").hidden = Boolean(frame);
    if (!frame) {
      $("frame-caption").textContent = "";
      await showPicture("frame-picture", null);
      return;
    }
    const what = frame.image_kept ? "overlay" : "top-down map";
    const violations = frame.violations === null ? "" : `, ${frame.violations} too close`;
    $("frame-caption").textContent = `${time(frame.timestamp)} · ${frame.people} people${violations} · ${what}`;
    await showPicture("frame-picture", frame.image_kept ? frame.links.overlay : frame.links.topdown);
  }

  async function drawViolations(id, counts) {
    $("violations-total").textContent = `${counts.total} in all`;
    const box = $("violations");
    box.replaceChildren(bars(counts));
    // The heat map is drawn again when its data changes (or another hour begins), not on every refresh.
    const hour = new Date().toISOString().slice(0, 13);
    const source = `${cameraPath(id)}/violations/heatmap.png?bucket=hour&size_px=640`;
    await showPicture("heatmap", source, `${source} ${counts.total} ${hour}`);
  }

  // Violations per hour across the window, one bar per hour, empty hours included.
  function bars(counts) {
    const W = 400, H = 110, top = 12, bottom = 16;
    const since = Date.parse(counts.since), until = Date.parse(counts.until), step = counts.bucket_s * 1000;
    const first = Math.floor(since / step) * step;
    const n = Math.max(1, Math.ceil((until - first) / step));
    const byStart = new Map(counts.buckets.map((b) => [Date.parse(b.start), b.count]));
    const most = Math.max(0, ...counts.buckets.map((b) => b.count));
    const peak = Math.max(1, most);
    const figure = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "chart bars", role: "img" });
    figure.append(svg("title", {}, `violations per ${counts.bucket}`));
    const width = W / n;
    for (let k = 0; k < n; k++) {
      const start = first + k * step;
      const count = byStart.get(start) || 0;
      const h = ((H - top - bottom) * count) / peak;
      const bar = svg("rect", { x: (k * width + 1).toFixed(1), y: (H - bottom - h).toFixed(1), width: Math.max(1, width - 2).toFixed(1), height: h.toFixed(1), class: "bar" });
      bar.append(svg("title", {}, `${new Date(start).toISOString().slice(0, 16).replace("T", " ")} UTC: ${count}`));
      figure.append(bar);
    }
    figure.append(svg("line", { x1: 0, x2: W, y1: H - bottom, y2: H - bottom, class: "axis-line" }));
    figure.append(svg("text", { x: 2, y: H - 4, class: "axis" }, time(counts.since).slice(0, 16)));
    figure.append(svg("text", { x: W - 2, y: H - 4, class: "axis", "text-anchor": "end" }, `${time(counts.until).slice(0, 16)} UTC`));
    figure.append(svg("text", { x: W - 2, y: top + 2, class: "axis", "text-anchor": "end" }, most ? `max ${most} per ${counts.bucket}` : "none"));
    return figure;
  }

  // ------------------------------------------------------------------------------------------------- webhooks

  async function drawWebhooks() {
    const body = $("webhooks").querySelector("tbody");
    const note = $("webhooks-note");
    if (!caller.admin) {
      body.replaceChildren();
      $("webhooks").hidden = true;
      note.hidden = false;
      note.textContent = "Webhook subscriptions are managed with admin keys; this key is not one.";
      return;
    }
    const subscriptions = (await api("/v1/webhooks?limit=100")).items;
    const failed = await Promise.all(
      subscriptions.map((s) => api(`/v1/webhooks/${encodeURIComponent(s.id)}/deliveries?status=failed&limit=5`)),
    );
    body.replaceChildren();
    subscriptions.forEach((s, k) => {
      const failures = failed[k];
      const row = element("tr");
      const state = s.enabled ? "enabled" : `disabled${s.disabled_reason ? `: ${s.disabled_reason}` : ""}`;
      const cell = element("td");
      if (failures.items.length) {
        const newest = failures.items[0];
        const answer = newest.last_status_code ? `HTTP ${newest.last_status_code}` : newest.last_error || "no answer";
        const count = failures.next_before ? `${failures.items.length}+` : String(failures.items.length);
        cell.append(element("span", `${count} failed`, "error"), element("span", ` · newest ${time(newest.created_at)}: ${answer}`, "muted"));
      } else {
        cell.append(element("span", "none", "muted"));
      }
      row.append(element("td", s.url, "url"), element("td", s.event_types.join(", ")), element("td", state), cell);
      body.append(row);
    });
    $("webhooks").hidden = subscriptions.length === 0;
    note.hidden = subscriptions.length > 0;
    note.textContent = "No subscriptions: POST /v1/webhooks adds one.";
  }

  // ------------------------------------------------------------------------------------------------- wiring

  document.addEventListener("DOMContentLoaded", () => {
    $("key-form").addEventListener("submit", (event) => {
      event.preventDefault();
      const input = $("key");
      const key = input.value.trim();
      input.value = "";
      if (!key) return;
      sessionStorage.setItem(KEY_STORAGE, key);
      start();
    });
    $("sign-out").addEventListener("click", () => signOut(""));
    if (sessionStorage.getItem(KEY_STORAGE)) start();
  });
})();
