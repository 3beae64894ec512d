"""The console's HTML, rendered on the server: the layout and its empty panels, which console.js fills."""

from __future__ import annotations

import html
from pathlib import Path
from string import Template

STATIC_DIR = Path(__file__).resolve().parent / "static"

_PAGE = Template("""<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>posemetry console</title>
<link rel="icon" href="/console/icon.svg" type="image/svg+xml">
<link rel="stylesheet" href="/console/console.css">
<script src="/console/console.js" defer></script>
</head>
<body data-refresh-s="$refresh_s">
<header class="bar">
  <h1>posemetry <span class="muted">console</span></h1>
  <span class="muted" id="who"></span>
  <span class="spacer"></span>
  <span class="muted" id="refreshed"></span>
  <button type="button" id="sign-out" hidden>Forget key</button>
</header>
<main>
  <section id="login" class="card narrow">
    <h2>API key</h2>
    <p class="muted">The key stays in this browser tab (session storage) and is sent only as an
    <code>Authorization: Bearer</code> header to this API. A key limited to some cameras shows only those.</p>
    <form id="key-form" method="post" autocomplete="off">
      <input id="key" name="key" type="password" placeholder="pm_..." spellcheck="false" required>
      <button type="submit">Open</button>
    </form>
    <p id="error" class="error" role="alert" hidden></p>
  </section>
  <div id="dashboard" hidden>
    <section class="card">
      <h2>Cameras</h2>
      <table id="cameras">
        <thead><tr><th>camera</th><th>status</th><th>quality</th><th>people still needed</th>
        <th>focal length</th><th>height</th></tr></thead>
        <tbody></tbody>
      </table>
      <p id="no-cameras" class="muted" hidden>No cameras yet: <code>PUT /v1/cameras/{id}</code> creates one.</p>
    </section>
    <div id="camera" class="grid" hidden>
      <section class="card">
        <h2>Calibration history <span class="muted" id="history-camera"></span></h2>
        <div id="history" class="charts"></div>
      </section>
      <section class="card">
        <h2>Latest frame <span class="muted" id="frame-caption"></span></h2>
        <img id="frame-picture" class="picture" alt="the latest measured frame" hidden>
        <p id="no-frame" class="muted" hidden>No measured frame yet.</p>
      </section>
      <section class="card">
        <h2>Violations, last 24 h <span class="muted" id="violations-total"></span></h2>
        <div id="violations"></div>
        <img id="heatmap" class="picture" alt="where and when violations happened, last 24 h" hidden>
      </section>
    </div>
    <section class="card" id="webhooks-card">
      <h2>Webhook subscriptions</h2>
      <table id="webhooks">
        <thead><tr><th>receiver</th><th>events</th><th>state</th><th>failing deliveries</th></tr></thead>
        <tbody></tbody>
      </table>
      <p id="webhooks-note" class="muted" hidden></p>
    </section>
  </div>
</main>
<footer class="muted">posemetry $version · refreshes every $refresh_s s · <a href="/docs">API documentation</a></footer>
</body>
</html>
""")


def render_page(version: str, refresh_s: float) -> str:
    return _PAGE.substitute(version=html.escape(version), refresh_s=f"{refresh_s:g}")
