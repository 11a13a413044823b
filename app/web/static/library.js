// The Library view: scan a folder of the server, review each suggestion (accept, move the pin, reject),
// write the accepted positions back, undo, export. Plain JS, no build step. File names, labels and
// messages reach the page as text nodes only (never as HTML), map popups included.
"use strict";

const $ = (id) => document.getElementById(id);
const hasLeaflet = typeof window.L !== "undefined";
let scanId = new URLSearchParams(location.search).get("scan");
let photos = [];
let selected = null; // the photo whose pin the map shows
let moved = null; // [lat, lon] clicked on the map for the selected photo

$("api-key").value = sessionStorage.getItem("geoloc-key") || "";
$("api-key").addEventListener("input", (e) => sessionStorage.setItem("geoloc-key", e.target.value));
const keyHeaders = () => ($("api-key").value ? { "X-API-Key": $("api-key").value } : {});

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (name === "class") e.className = value;
    else e.setAttribute(name, value);
  }
  e.append(...children.filter((c) => c != null && c !== ""));
  return e;
}
function showError(message) { $("lib-error").textContent = message; $("lib-error").hidden = !message; }
function status(text) { $("lib-status").textContent = text; }

async function api(path, options = {}) {
  const response = await fetch(path, { ...options, headers: { ...keyHeaders(), ...(options.headers || {}) } });
  const type = response.headers.get("content-type") || "";
  const body = type.includes("json") ? await response.json() : await response.blob();
  if (!response.ok) throw new Error(`${response.status}: ${body && body.message ? body.message : response.statusText}`);
  return body;
}
const post = (path, body) =>
  api(path, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body || {}) });

// -- the map ---------------------------------------------------------------------------------------------
let map = null, layer = null;
if (hasLeaflet) {
  map = L.map("lib-map").setView([39.9522, -75.1932], 16);
  L.tileLayer("https://tile.openstreetmap.org/{z}/{x}/{y}.png", { maxZoom: 19, attribution: "© OpenStreetMap contributors" }).addTo(map);
  layer = L.layerGroup().addTo(map);
  map.on("click", (e) => {
    if (!selected) return;
    moved = [e.latlng.lat, e.latlng.lng];
    drawPin(selected);
    render();
  });
} else {
  $("lib-map").textContent = "The map library did not load; suggestions are listed beside.";
}

function drawPin(p) {
  if (!layer) return;
  layer.clearLayers();
  for (const c of p.candidates || []) {
    L.circleMarker([c.lat, c.lon], { radius: 4, color: "#555" }).addTo(layer)
      .bindTooltip(el("span", {}, `${c.label || "reference"} (${c.score})`));
  }
  const where = moved || (p.accepted_lat != null ? [p.accepted_lat, p.accepted_lon] : p.placed ? [p.lat, p.lon] : null);
  if (!where) return;
  if (p.radius_m && !moved) L.circle(where, { radius: p.radius_m, color: "#1f5fbf", weight: 1 }).addTo(layer);
  L.marker(where).addTo(layer).bindTooltip(el("span", {}, p.file.split("/").pop()));
  map.setView(where, Math.max(map.getZoom(), 17));
}

// -- the list ---------------------------------------------------------------------------------------------
function badge(p) {
  if (p.kind === "problem") return el("span", { class: "badge none" }, "not readable");
  if (p.confident) return el("span", { class: "badge confident" }, "confident");
  if (p.placed) return el("span", { class: "badge unsure" }, "not confident");
  return el("span", { class: "badge none" }, "no position");
}

function summary(p) {
  if (p.kind === "problem") return p.reason;
  if (!p.placed) return `${p.reason_code || ""}: ${p.reason || ""}`;
  const basis = p.basis === "sequence" ? "the run of photos around it" : p.basis;
  return `${p.lat.toFixed(6)}, ${p.lon.toFixed(6)} ± ${p.radius_m} m, from ${basis}` + (p.p != null ? `, p ${p.p}` : "");
}

// photo id -> a promise of its object URL (fetched once with the key header, shown as blob:): the poll
// re-renders the list every second while a scan runs, and must not fetch a thumbnail again each time.
const thumbs = new Map();
function clearThumbs() {
  for (const url of thumbs.values()) url.then((u) => u && URL.revokeObjectURL(u));
  thumbs.clear();
}
async function thumb(img, p) {
  if (!thumbs.has(p.id)) {
    thumbs.set(p.id, api(`/library/scans/${scanId}/photos/${p.id}/thumbnail`)
      .then((blob) => URL.createObjectURL(blob))
      .catch(() => { thumbs.delete(p.id); return null; }));
  }
  const url = await thumbs.get(p.id);
  if (url) img.src = url;
}
// Thumbnails are fetched when their row comes near the viewport (a library lists thousands of photos).
const lazy = "IntersectionObserver" in window
  ? new IntersectionObserver((entries) => {
    for (const e of entries) {
      if (!e.isIntersecting) continue;
      lazy.unobserve(e.target);
      const p = photos.find((q) => String(q.id) === e.target.dataset.photo);
      if (p) thumb(e.target, p);
    }
  }, { rootMargin: "200px" })
  : null;

async function decide(p, action, extra = {}) {
  showError("");
  try {
    const got = await post(`/library/scans/${scanId}/photos/${p.id}/decision`, { action, ...extra });
    photos = photos.map((q) => (q.id === got.id ? got : q));
    if (selected && selected.id === got.id) selected = got;
    moved = null;
    render();
  } catch (e) { showError(e.message); }
}

function render() {
  const list = $("lib-photos");
  if (lazy) lazy.disconnect(); // the rows below replace the observed ones
  list.replaceChildren();
  for (const p of photos) {
    const img = el("img", { alt: "", "data-photo": String(p.id) });
    if (p.kind !== "problem") { if (lazy) lazy.observe(img); else thumb(img, p); }
    const cands = el("ol", { class: "cands", "aria-label": "candidates" },
      ...(p.candidates || []).slice(0, 3).map((c) => el("li", {}, `${c.lat.toFixed(5)}, ${c.lon.toFixed(5)} (${c.score})`)));
    const buttons = [];
    if (p.kind !== "problem") {
      const accept = el("button", { type: "button", class: "accept" }, "Accept");
      accept.disabled = !p.placed;
      accept.addEventListener("click", () => decide(p, "accept"));
      const reject = el("button", { type: "button", class: "reject" }, "Reject");
      reject.addEventListener("click", () => decide(p, "reject"));
      buttons.push(accept, reject);
      if (selected && selected.id === p.id && moved) {
        const here = el("button", { type: "button", class: "move" }, "Accept here");
        here.addEventListener("click", () => decide(p, "move", { lat: moved[0], lon: moved[1] }));
        buttons.push(here);
      }
    }
    const decision = p.decision
      ? el("span", { class: "decision" }, p.decision + (p.written ? ` (written: ${p.written.mode})` : ""))
      : null;
    const item = el("li", { class: "photo" + (selected && selected.id === p.id ? " selected" : ""), "data-file": p.file },
      img,
      el("div", { class: "body" },
        el("div", { class: "name" }, p.file.split("/").pop()),
        el("div", {}, badge(p), " ", summary(p)),
        cands, el("div", {}, ...buttons, " ", decision)));
    item.addEventListener("click", (e) => {
      if (e.target.tagName === "BUTTON") return;
      if (!selected || selected.id !== p.id) moved = null;
      selected = p;
      drawPin(p);
      render();
    });
    list.append(item);
  }
}

// -- scan, poll, write, undo, export ---------------------------------------------------------------------------
let shown = ""; // the photos last rendered, as JSON: a poll that changed nothing renders nothing
async function load() {
  const scan = await api(`/library/scans/${scanId}`);
  photos = scan.photos;
  $("lib-actions").hidden = false;
  status(`${scan.folder}: ${scan.state}, ${scan.done} photos located by this run (${scan.total} in the folder)` +
    (scan.message ? `: ${scan.message}` : ""));
  const now = JSON.stringify(photos);
  if (now !== shown) { shown = now; render(); }
  if (scan.state === "running") setTimeout(() => load().catch((e) => showError(e.message)), 1000);
}

// A server with no GEOLOC_LIBRARY_ROOT scans no folder: its page (the /library route fills in
// data-scans-folders) says so and offers no Scan that could only be refused. Served any other way
// ("unknown"), the form stays and the API answers for itself.
if (document.body.dataset.scansFolders === "no") {
  $("scan-form").hidden = true;
  $("scan-btn").disabled = true;
  $("scan-off").hidden = false;
}

$("scan-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  showError("");
  try {
    const got = await post("/library/scans", { folder: $("scan-folder").value, time_prior: $("scan-time").checked });
    if (got.id !== scanId) clearThumbs();
    scanId = got.id;
    history.replaceState(null, "", `/library?scan=${scanId}`);
    status("scanning...");
    await load();
  } catch (err) { showError(err.message); }
});

$("write-btn").addEventListener("click", async () => {
  showError("");
  try {
    const out = await post(`/library/scans/${scanId}/write`, { in_file: $("write-infile").checked, dry_run: $("write-dry").checked });
    $("write-result").textContent = `${out.dry_run ? "would write" : "wrote"} ${out.written.length}, failed ${out.failed.length}`;
    await load();
  } catch (err) { showError(err.message); }
});

$("undo-btn").addEventListener("click", async () => {
  showError("");
  try {
    const out = await post(`/library/scans/${scanId}/undo`);
    $("write-result").textContent = `undid ${out.restored.length} writes`;
    await load();
  } catch (err) { showError(err.message); }
});

for (const b of document.querySelectorAll(".export")) {
  b.addEventListener("click", async () => {
    try {
      const url = `/library/scans/${scanId}/export?format=${b.dataset.format}&all=${$("export-all").checked}`;
      const response = await fetch(url, { headers: keyHeaders() });
      if (!response.ok) throw new Error(`${response.status}: ${response.statusText}`);
      const blob = await response.blob();
      const a = el("a", { href: URL.createObjectURL(blob), download: `library.${b.dataset.format}` });
      a.click();
    } catch (err) { showError(err.message); }
  });
}

if (scanId) load().catch((e) => showError(e.message));
