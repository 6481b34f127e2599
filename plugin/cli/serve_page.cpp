// The page `posecal serve` sends at "/": the station's cameras in a grid, each live (its MJPEG
// stream with the operator overlay) with state, keyframes, expected error and verdict, and the
// buttons to start, abort and close sessions. One document, no external resources and no
// JavaScript build step; it uses only the REST routes a controller uses (docs/serve.md). A page
// opened as /?token=T sends the token with every request.
#include "station_server.hpp"

namespace posecal::cli {

const char* serve_page_html() {
  return R"PAGE(<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>posecal station</title>
<style>
  body { font-family: sans-serif; margin: 0; background: #1d2126; color: #e8e8e8; }
  header { padding: 10px 16px; background: #2a3038; display: flex; gap: 12px; align-items: center;
           flex-wrap: wrap; }
  header h1 { font-size: 18px; margin: 0 12px 0 0; }
  input, button { font-size: 14px; padding: 5px 8px; border-radius: 4px; border: 1px solid #566; }
  input { background: #111; color: #eee; }
  input#camera { width: 22em; } input#config { width: 26em; }
  button { background: #3b6ea5; color: white; cursor: pointer; }
  button.stop { background: #a5523b; }
  #grid { display: grid; grid-template-columns: repeat(auto-fill, minmax(420px, 1fr)); gap: 12px;
          padding: 12px; }
  .tile { background: #2a3038; border-radius: 6px; overflow: hidden; }
  .tile img { width: 100%; display: block; background: #000; min-height: 120px; }
  .info { padding: 8px 10px; font-size: 14px; line-height: 1.5; }
  .state { font-weight: bold; }
  .converged { color: #6fdc6f; } .failed, .error { color: #ff7b6b; }
  .bar { height: 6px; background: #444; border-radius: 3px; margin: 4px 0; }
  .bar div { height: 6px; background: #6fb1ff; border-radius: 3px; }
  #message { color: #ff7b6b; }
</style>
</head>
<body>
<header>
  <h1>posecal station</h1>
  <input id="camera" value="sim://?seed=1" aria-label="camera URI">
  <input id="config" value="{}" aria-label="session config (JSON)">
  <button id="start">Start</button>
  <span id="message"></span>
</header>
<div id="grid"></div>
<script>
"use strict";
const params = new URLSearchParams(location.search);
const token = params.get("token");
// ?view=snapshots: a picture a second (frame.jpg) instead of the MJPEG stream, for clients that
// wait for every request to end (a headless browser's screenshot).
const snapshots = params.get("view") === "snapshots";
let tick = 0;
function withToken(url) {
  return token ? url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : url;
}
async function api(method, url, body) {
  const r = await fetch(withToken(url), {method, body: body === undefined ? undefined : JSON.stringify(body),
                                         headers: body === undefined ? {} : {"Content-Type": "application/json"}});
  const j = await r.json().catch(() => ({error: r.statusText}));
  if (!r.ok) throw new Error(j.error || r.statusText);
  return j;
}
function text(el, s) { el.textContent = s; return el; }
function make(tag, cls) { const e = document.createElement(tag); if (cls) e.className = cls; return e; }
const tiles = new Map();
function tile(s) {
  let t = tiles.get(s.id);
  if (!t) {
    t = {root: make("div", "tile")};
    t.img = make("img"); t.img.alt = s.camera;
    if (!snapshots) t.img.src = withToken("/api/sessions/" + s.id + "/stream.mjpg");
    t.info = make("div", "info");
    t.title = make("div"); t.state = make("div", "state"); t.detail = make("div");
    t.bar = make("div", "bar"); t.fill = make("div"); t.bar.appendChild(t.fill);
    const abort = text(make("button", "stop"), "Stop");
    abort.onclick = () => api("POST", "/api/sessions/" + s.id + "/abort").catch(e => say(e.message));
    const close = text(make("button", "stop"), "Close");
    close.onclick = () => api("DELETE", "/api/sessions/" + s.id).then(refresh).catch(e => say(e.message));
    t.info.append(t.title, t.state, t.bar, t.detail, abort, document.createTextNode(" "), close);
    t.root.append(t.img, t.info);
    document.getElementById("grid").appendChild(t.root);
    tiles.set(s.id, t);
  }
  if (snapshots && !(s.done && t.img.src)) t.img.src = withToken("/api/sessions/" + s.id + "/frame.jpg?n=" + tick);
  text(t.title, s.id + "  " + s.camera);
  const state = s.error ? "error: " + s.error : s.interrupted ? "stopped" :
                !s.camera_connected ? "camera disconnected (waiting for it to come back)" : s.state;
  text(t.state, state).className = "state " + (s.converged ? "converged" :
                                               s.error || !s.camera_connected ? "error" :
                                               s.finished ? "failed" : "");
  const max = (s.max_keyframes || 20);
  t.fill.style.width = Math.min(100, 100 * s.keyframes / max) + "%";
  let d = s.keyframes + (s.keyframes === 1 ? " keyframe" : " keyframes");
  if (s.expected_error_px != null) d += ", expected error " + Number(s.expected_error_px).toFixed(3) + " px";
  if (s.verdict) d += ", verdict " + s.verdict;
  if (!s.finished && s.guidance) d += " \u2014 " + s.guidance;
  text(t.detail, d);
}
function say(m) { text(document.getElementById("message"), m); }
async function refresh() {
  try {
    const list = await api("GET", "/api/sessions");
    ++tick;
    const ids = new Set(list.map(s => s.id));
    for (const [id, t] of tiles) if (!ids.has(id)) { t.img.src = ""; t.root.remove(); tiles.delete(id); }
    list.forEach(tile);
  } catch (e) { say(e.message); }
}
document.getElementById("start").onclick = async () => {
  say("");
  try {
    const config = JSON.parse(document.getElementById("config").value || "{}");
    await api("POST", "/api/sessions", {camera: document.getElementById("camera").value, config});
    refresh();
  } catch (e) { say(e.message); }
};
refresh();
setInterval(refresh, 1000);
</script>
</body>
</html>
)PAGE";
}

}  // namespace posecal::cli
