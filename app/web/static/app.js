// The geoloc page: locate a photo, browse/add/delete references. Plain JS, no build step.
// Map tiles come over the user's network and may be missing: markers, the estimate and the lists are
// drawn whatever the tiles do, and the page works without Leaflet at all (lists only).
"use strict";

const $ = (id) => document.getElementById(id);
const hasLeaflet = typeof window.L !== "undefined";
const PAGE = 20;
let refsOffset = 0;

// -- API key: kept for this browser session only --------------------------------------------------
$("api-key").value = sessionStorage.getItem("geoloc-key") || "";
$("api-key").addEventListener("input", (e) => sessionStorage.setItem("geoloc-key", e.target.value));
const keyHeaders = () => ($("api-key").value ? { "X-API-Key": $("api-key").value } : {});

function showError(message) {
  const box = $("error");
  box.textContent = message;
  box.hidden = !message;
}
function status(text) { $("status").textContent = text; }

async function api(path, options = {}) {
  let response;
  try {
    response = await fetch(path, options);
  } catch (e) {
    throw new Error("The service cannot be reached: " + e.message);
  }
  const type = response.headers.get("content-type") || "";
  const body = type.includes("json") ? await response.json() : null;
  if (!response.ok) {
    const why = body && body.message ? body.message : response.statusText;
    throw new Error(`${response.status}: ${why}`);
  }
  return body;
}

// -- maps -------------------------------------------------------------------------------------------
function makeMap(id) {
  if (!hasLeaflet) {
    $(id).textContent = "The map library did not load; results are listed beside.";
    return null;
  }
  const map = L.map(id, { zoomControl: true }).setView([39.9522, -75.1932], 16);
  L.tileLayer("https://tile.openstreetmap.org/{z}/{x}/{y}.png", {
    maxZoom: 19,
    attribution: "&copy; OpenStreetMap contributors",
  }).addTo(map);
  return { map, layer: L.layerGroup().addTo(map) };
}
const locateMap = makeMap("map");
const refsMap = makeMap("refs-map");

function numberedIcon(n) {
  return L.divIcon({ className: "num-marker", html: `<span>${n}</span>`, iconSize: [26, 26] });
}

// -- tabs -------------------------------------------------------------------------------------------
function select(tab) {
  for (const [t, v] of [["tab-locate", "view-locate"], ["tab-refs", "view-refs"]]) {
    const on = t === tab;
    $(t).setAttribute("aria-selected", String(on));
    $(v).hidden = !on;
  }
  showError("");
  if (tab === "tab-refs") loadRefs();
  setTimeout(() => [locateMap, refsMap].forEach((m) => m && m.map.invalidateSize()), 0);
}
$("tab-locate").addEventListener("click", () => select("tab-locate"));
$("tab-refs").addEventListener("click", () => select("tab-refs"));

// -- locate -----------------------------------------------------------------------------------------
const drop = $("drop");
["dragenter", "dragover"].forEach((ev) => drop.addEventListener(ev, (e) => { e.preventDefault(); drop.classList.add("over"); }));
["dragleave", "drop"].forEach((ev) => drop.addEventListener(ev, () => drop.classList.remove("over")));
drop.addEventListener("drop", (e) => {
  e.preventDefault();
  if (e.dataTransfer.files.length) {
    $("locate-file").files = e.dataTransfer.files;
    locate();
  }
});
drop.addEventListener("keydown", (e) => { if (e.key === "Enter" || e.key === " ") { e.preventDefault(); $("locate-file").click(); } });
$("locate-form").addEventListener("submit", (e) => { e.preventDefault(); locate(); });

async function locate() {
  const file = $("locate-file").files[0];
  if (!file) { showError("Choose a photo first."); return; }
  showError("");
  status("Locating…");
  const form = new FormData();
  form.append("image", file);
  form.append("top_k", $("top-k").value || "10");
  try {
    const res = await api("/locate", { method: "POST", body: form, headers: keyHeaders() });
    renderLocate(res);
    status(`${res.candidates.length} candidates in ${Math.round(res.timings_ms.total)} ms ` +
           `(${res.features.kept} of ${res.features.extracted} features used).`);
  } catch (e) {
    status("");
    showError(e.message);
  }
}

function renderLocate(res) {
  const list = $("candidates");
  list.replaceChildren();
  const est = res.estimate;
  $("estimate").textContent = est
    ? `Estimate: ${est.lat.toFixed(6)}, ${est.lon.toFixed(6)} within ${Math.round(est.radius_m)} m ` +
      `(confidence ${(est.confidence * 100).toFixed(0)} %).`
    : `No confident estimate: ${res.reason || "the candidates disagree"}.`;
  res.candidates.forEach((c, i) => {
    const li = document.createElement("li");
    li.className = "candidate";
    const img = document.createElement("img");
    img.src = `/references/${c.reference_id}/image`;
    img.alt = `Reference ${c.reference_id}${c.label ? ": " + c.label : ""}`;
    const text = document.createElement("div");
    const dist = c.distance_m == null ? "" : `, ${Math.round(c.distance_m)} m from the estimate`;
    text.innerHTML = `<strong>${i + 1}. ${escapeHtml(c.label || "reference " + c.reference_id)}</strong>` +
      `<br>score ${c.score.toFixed(3)}${dist}<br><small>${c.lat.toFixed(6)}, ${c.lon.toFixed(6)}</small>`;
    li.append(img, text);
    list.append(li);
  });
  if (!locateMap) return;
  const { map, layer } = locateMap;
  layer.clearLayers();
  const pts = [];
  res.candidates.forEach((c, i) => {
    L.marker([c.lat, c.lon], { icon: numberedIcon(i + 1), title: `Candidate ${i + 1}`, alt: `Candidate ${i + 1}` })
      .bindPopup(`${i + 1}. ${escapeHtml(c.label || "reference " + c.reference_id)} (score ${c.score.toFixed(3)})`)
      .addTo(layer);
    pts.push([c.lat, c.lon]);
  });
  if (est) {
    L.circle([est.lat, est.lon], { radius: est.radius_m, color: "#d33", weight: 2, fillOpacity: 0.15 })
      .bindTooltip("Estimate").addTo(layer);
    L.circleMarker([est.lat, est.lon], { radius: 6, color: "#d33", fillOpacity: 1, className: "estimate-marker" })
      .addTo(layer);
    pts.push([est.lat, est.lon]);
  }
  if (pts.length) map.fitBounds(pts, { padding: [30, 30], maxZoom: 18 });
}

function escapeHtml(s) {
  return String(s).replace(/[&<>"']/g, (ch) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[ch]);
}

// -- references -------------------------------------------------------------------------------------
async function loadRefs() {
  try {
    const page = await api(`/references?offset=${refsOffset}&limit=${PAGE}`, { headers: keyHeaders() });
    renderRefs(page);
  } catch (e) {
    showError(e.message);
  }
}

function renderRefs(page) {
  $("refs-count").textContent = page.total
    ? `References ${page.offset + 1}–${page.offset + page.items.length} of ${page.total}`
    : "No references yet.";
  $("prev").disabled = page.offset === 0;
  $("next").disabled = page.offset + page.items.length >= page.total;
  const ul = $("refs");
  ul.replaceChildren();
  for (const r of page.items) {
    const li = document.createElement("li");
    li.className = "ref";
    const img = document.createElement("img");
    img.src = `/references/${r.id}/image`;
    img.alt = `Reference ${r.id}${r.label ? ": " + r.label : ""}`;
    img.loading = "lazy";
    const text = document.createElement("div");
    text.innerHTML = `<strong>${escapeHtml(r.label || "reference " + r.id)}</strong><br>` +
      `<small>${r.lat.toFixed(6)}, ${r.lon.toFixed(6)} · ${escapeHtml(r.status)}</small>`;
    const del = document.createElement("button");
    del.type = "button";
    del.textContent = "Delete";
    del.setAttribute("aria-label", `Delete reference ${r.id}`);
    del.addEventListener("click", () => deleteRef(r.id));
    li.append(img, text, del);
    ul.append(li);
  }
  if (refsMap) {
    refsMap.layer.clearLayers();
    const pts = page.items.map((r) => [r.lat, r.lon]);
    page.items.forEach((r) => L.circleMarker([r.lat, r.lon], { radius: 5 }).bindTooltip(r.label || `#${r.id}`).addTo(refsMap.layer));
    if (pts.length) refsMap.map.fitBounds(pts, { padding: [30, 30], maxZoom: 18 });
  }
}

async function deleteRef(id) {
  if (!confirm(`Delete reference ${id}? Its image, codes and metadata are removed.`)) return;
  try {
    await api(`/references/${id}`, { method: "DELETE", headers: keyHeaders() });
    showError("");
    status(`Reference ${id} deleted.`);
    loadRefs();
  } catch (e) {
    showError(e.message);
  }
}

$("prev").addEventListener("click", () => { refsOffset = Math.max(0, refsOffset - PAGE); loadRefs(); });
$("next").addEventListener("click", () => { refsOffset += PAGE; loadRefs(); });

if (refsMap) {
  let pick = null;
  refsMap.map.on("click", (e) => {
    $("add-lat").value = e.latlng.lat.toFixed(7);
    $("add-lon").value = e.latlng.lng.toFixed(7);
    if (pick) pick.remove();
    pick = L.marker(e.latlng, { title: "New reference position" }).addTo(refsMap.map);
  });
}

$("add-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const file = $("add-file").files[0];
  if (!file) { showError("Choose an image to add."); return; }
  const form = new FormData();
  form.append("image", file);
  for (const [id, name] of [["add-lat", "lat"], ["add-lon", "lon"], ["add-label", "label"]]) {
    if ($(id).value.trim()) form.append(name, $(id).value.trim());
  }
  showError("");
  try {
    const res = await api("/references", { method: "POST", body: form, headers: keyHeaders() });
    status(res.duplicates[0] ? `Already stored as reference ${res.reference_ids[0]}.`
                             : `Accepted as reference ${res.reference_ids[0]}; encoding…`);
    await waitJob(res.job_id);
    loadRefs();
  } catch (err) {
    showError(err.message);
  }
});

async function waitJob(id) {
  for (let i = 0; i < 120; i++) {
    const job = await api(`/jobs/${id}`, { headers: keyHeaders() });
    if (job.status === "done" || job.status === "failed") {
      status(job.status === "done" ? "Reference indexed." : `Encoding failed: ${job.items[0].error}`);
      return job;
    }
    await new Promise((r) => setTimeout(r, 500));
  }
}
