// The geoloc page: locate a photo, browse/add/delete references. Plain JS, no build step.
// Map tiles come over the user's network and may be missing: markers, the estimate and the lists are
// drawn whatever the tiles do, and the page works without Leaflet at all (lists only).
"use strict";

const $ = (id) => document.getElementById(id);
const hasLeaflet = typeof window.L !== "undefined";
const PAGE = 20;
// The references list pages by id (after= / before=): a page deep in 10^6 references costs what the first
// does, where an offset would make the server skip every row before it.
const LAST_PAGE = "before=9223372036854775807";
let refsCursor = "after=0";
let lastPage = null; // the page shown: its next_after / prev_before are the cursors of its neighbours
let candidateMarkers = []; // the locate map's markers, by rank
let photoMarkers = []; // a sequence's markers, by photo (none where a photo has no place)

// -- API key: kept for this browser session only --------------------------------------------------
$("api-key").value = sessionStorage.getItem("geoloc-key") || "";
$("api-key").addEventListener("input", (e) => sessionStorage.setItem("geoloc-key", e.target.value));
const keyHeaders = () => ($("api-key").value ? { "X-API-Key": $("api-key").value } : {});

// Each view has its own status line and error box ("locate" or "refs"), so a message never shows up
// on the other tab.
function showError(view, message) {
  const box = $(`${view}-error`);
  box.textContent = message;
  box.hidden = !message;
}
function status(view, text) { $(`${view}-status`).textContent = text; }

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

// -- building the page -------------------------------------------------------------------------------
// Labels, file names, notes and messages come from users and the service: they reach the page as text
// nodes only, never as a string of HTML (a label in a map tooltip once ran as script and sent the API key
// away). Elements are built here; a string child becomes text. Leaflet gets nodes, not strings, too.
function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (name === "class") e.className = value;
    else e.setAttribute(name, value);
  }
  e.append(...children.filter((c) => c != null && c !== ""));
  return e;
}
// The parts (nodes or strings; empty ones left out) with a line break between each.
function lines(...parts) {
  return parts.filter((p) => p != null && p !== "").flatMap((p, k) => (k ? [el("br"), p] : [p]));
}
const textNode = (s) => document.createTextNode(s);

// -- words ------------------------------------------------------------------------------------------
const position = (lat, lon) => `${lat.toFixed(5)}, ${lon.toFixed(5)}`;
const metres = (m) => (m < 1000 ? `${Math.round(m)} m` : `${(m / 1000).toFixed(1)} km`);

// Labels are often the uploaded file's name (`geoloc ingest` uses it): that says nothing about the
// place, so such a reference is called by its id and the file name is kept as a small detail (it is
// still how its owner finds the photo on disk). A real label ("College Hall") is the title.
const FILE_NAME = /^[^\s/\\]+\.(jpe?g|png|webp|tiff?|heic|heif|gif|bmp)$/i;
function refName(id, label) {
  if (label && !FILE_NAME.test(label.trim())) return { title: label, file: "" };
  return { title: `Reference #${id}`, file: label || "" };
}

function haversine(a, b) {
  const rad = Math.PI / 180, R = 6371008.8;
  const dlat = (b.lat - a.lat) * rad, dlon = (b.lon - a.lon) * rad;
  const h = Math.sin(dlat / 2) ** 2 + Math.cos(a.lat * rad) * Math.cos(b.lat * rad) * Math.sin(dlon / 2) ** 2;
  return 2 * R * Math.asin(Math.min(1, Math.sqrt(h)));
}
function spread(points) {
  let most = 0;
  points.forEach((p, i) => points.slice(i + 1).forEach((q) => { most = Math.max(most, haversine(p, q)); }));
  return most;
}

// -- maps -------------------------------------------------------------------------------------------
function makeMap(id) {
  if (!hasLeaflet) {
    $(id).textContent = "The map library did not load; results are listed beside.";
    return null;
  }
  const map = L.map(id, { zoomControl: true }).setView([39.9522, -75.1932], 16);
  const tiles = L.tileLayer("https://tile.openstreetmap.org/{z}/{x}/{y}.png", {
    maxZoom: 19,
    attribution: "© OpenStreetMap contributors", // Leaflet takes only a string here: ours, no user text
  }).addTo(map);
  L.control.scale({ imperial: false }).addTo(map);
  tiles.once("tileerror", () => noTiles(id));
  return { map, layer: L.layerGroup().addTo(map) };
}

// Without tiles the map is a blank plane: say so under it (never over the markers), so that nobody
// takes it for a broken page.
function noTiles(id) {
  $(id).classList.add("tiles-missing");
  const note = $(`${id}-note`);
  note.textContent = "The map background (tiles) could not load: positions are drawn to scale on a blank grid.";
  note.hidden = false;
}

const locateMap = makeMap("map");
const refsMap = makeMap("refs-map");

function numberedIcon(n, best) {
  const size = best ? 34 : 24;
  return L.divIcon({
    className: best ? "num-marker best" : "num-marker",
    html: el("span", {}, String(n)),
    iconSize: [size, size],
  });
}

// -- tabs: buttons with the tab pattern (arrow keys move between them, Enter/Space activate) --------
const TABS = [["tab-locate", "view-locate"], ["tab-refs", "view-refs"]];
function select(tab, focus = false) {
  for (const [t, v] of TABS) {
    const on = t === tab;
    $(t).setAttribute("aria-selected", String(on));
    $(t).tabIndex = on ? 0 : -1;
    $(v).hidden = !on;
  }
  if (focus) $(tab).focus();
  // The address names the view shown (/#references), so that a reload or a link opens the same one.
  history.replaceState(null, "", location.pathname + location.search + (tab === "tab-refs" ? "#references" : ""));
  if (tab === "tab-refs") loadRefs();
  setTimeout(() => [locateMap, refsMap].forEach((m) => m && m.map.invalidateSize()), 0);
}
TABS.forEach(([t], i) => {
  $(t).addEventListener("click", () => select(t));
  $(t).addEventListener("keydown", (e) => {
    const to = { ArrowRight: i + 1, ArrowLeft: i - 1, Home: 0, End: TABS.length - 1 }[e.key];
    if (to === undefined) return;
    e.preventDefault();
    select(TABS[(to + TABS.length) % TABS.length][0], true);
  });
});

// -- locate: the chosen photo -----------------------------------------------------------------------
let previewUrl = null;
let photoUrls = []; // the thumbnails of a sequence's photos, released when others are chosen
// The photos chosen, by file name (cameras and phones number their photos), numbers compared as numbers:
// the order of a sequence whose photos carry no capture times. The service orders those that do by their
// times (order=taken), whatever their names.
function chosenFiles() {
  return [...$("locate-file").files].sort((a, b) => a.name.localeCompare(b.name, "en", { numeric: true }));
}
function showPreview() {
  const files = chosenFiles();
  if (files.length > 1) { showSequencePreview(files); return; }
  const file = files[0];
  if (previewUrl) URL.revokeObjectURL(previewUrl);
  previewUrl = file ? URL.createObjectURL(file) : null;
  $("preview").hidden = false;
  $("preview").src = previewUrl || "";
  $("preview").alt = file ? `Your photo: ${file.name}` : "";
  $("preview-caption").textContent = "Your photo";
  $("preview-box").hidden = !file;
  clearAnswer();
  showError("locate", "");
  status("locate", file ? "Press Locate to find where it was taken." : "");
}
$("locate-file").addEventListener("change", showPreview);
// A format the browser cannot draw (TIFF in most browsers) can still be located: say so instead of
// showing a broken image.
$("preview").addEventListener("error", () => {
  if (!previewUrl) return;
  $("preview").hidden = true;
  $("preview-caption").textContent = "Your photo (this browser cannot show its format; it can still be located)";
});

// The answer, the candidates and the markers of the previous photo go as soon as another is chosen.
function clearAnswer() {
  $("answer").hidden = true;
  $("sequence").hidden = true;
  $("sequence-answers").replaceChildren();
  photoUrls.forEach((u) => URL.revokeObjectURL(u));
  photoUrls = [];
  photoMarkers = [];
  $("candidates").replaceChildren();
  $("legend").hidden = true;
  if (locateMap) locateMap.layer.clearLayers();
  candidateMarkers = [];
}

const drop = $("drop");
["dragenter", "dragover"].forEach((ev) => drop.addEventListener(ev, (e) => { e.preventDefault(); drop.classList.add("over"); }));
["dragleave", "drop"].forEach((ev) => drop.addEventListener(ev, () => drop.classList.remove("over")));
drop.addEventListener("drop", (e) => {
  e.preventDefault();
  if (e.dataTransfer.files.length) {
    $("locate-file").files = e.dataTransfer.files;
    showPreview();
    locate();
  }
});
$("locate-form").addEventListener("submit", (e) => { e.preventDefault(); locate(); });

async function locate() {
  const files = chosenFiles();
  if (files.length > 1) { locateSequence(files); return; }
  const file = files[0];
  if (!file) { showError("locate", "Choose a photo first."); return; }
  showError("locate", "");
  clearAnswer();
  status("locate", "Locating…");
  const region = regionOrSay();
  if (!region) return;
  $("locate-btn").disabled = true;
  const form = new FormData();
  form.append("image", file);
  form.append("top_k", $("top-k").value || "10");
  for (const [name, value] of Object.entries(region)) form.append(name, value);
  try {
    const res = await api("/locate", { method: "POST", body: form, headers: keyHeaders() });
    renderLocate(res);
    status("locate", `${res.candidates.length} candidates in ${Math.round(res.timings_ms.total)} ms.`);
  } catch (e) {
    status("locate", "");
    showError("locate", e.message);
    // The caption had promised that a photo the browser cannot draw "can still be located".
    if ($("preview").hidden) $("preview-caption").textContent = "Your photo (the service could not read it either: see below)";
  } finally {
    $("locate-btn").disabled = false;
  }
}

// -- locate: several photos as one path (POST /locate/sequence) ------------------------------------
function showSequencePreview(files) {
  if (previewUrl) URL.revokeObjectURL(previewUrl);
  previewUrl = null;
  $("preview-box").hidden = true;
  clearAnswer();
  showError("locate", "");
  status("locate", `${files.length} photos: press Locate to locate them as one path (a walk, a drive, a burst).`);
}

async function locateSequence(files) {
  showError("locate", "");
  clearAnswer();
  const region = regionOrSay();
  if (!region) return;
  status("locate", `Locating ${files.length} photos as one path…`);
  $("locate-btn").disabled = true;
  const form = new FormData();
  files.forEach((f) => form.append("image", f));
  form.append("order", "taken");
  form.append("top_k", $("top-k").value || "10");
  for (const [name, value] of Object.entries(region)) form.append(name, value);
  try {
    const res = await api("/locate/sequence", { method: "POST", body: form, headers: keyHeaders() });
    renderSequence(res, files);
    const ms = res.answers.reduce((t, a) => t + a.timings_ms.total, 0);
    status("locate", `${res.answers.length} photos located in ${Math.round(ms)} ms.`);
  } catch (e) {
    status("locate", "");
    showError("locate", namePhotos(e.message, files));
  } finally {
    $("locate-btn").disabled = false;
  }
}

// The service numbers a sequence's images from 0 in the order sent ("image 3: ..."): the page names that
// photo by its file name (its list numbers the photos in the order taken, which a refusal never reached).
function namePhotos(message, files) {
  return message.replace(/\bimage (\d+)\b/g, (whole, n) => (files[Number(n)] ? files[Number(n)].name : whole));
}

const TIMES_FROM = {
  exif: "in the order of the times they were taken (their EXIF)",
  given: "in the order of the times given",
  video: "in the order of the video's frames",
  order: "in the order of their file names (not every one carries a capture time)",
};

// What one photo's answer rests on, in words: the path only where the photo alone was not enough.
function restsOnInWords(a) {
  if (a.rests_on === "sequence") {
    const measured = a.estimate && a.estimate.radius_rate != null ? " (its disc measured on this collection's own walks)" : "";
    return `Placed by the path through the photos around it${measured}; alone, this photo was not enough.`;
  }
  if (a.estimate) return "From this photo alone.";
  return a.reason ? `No estimate: ${a.reason.replace(/\.$/, "")}.` : "No estimate.";
}

function sequenceItem(a, n, file) {
  const li = el("li", { class: "candidate" });
  const url = URL.createObjectURL(file);
  photoUrls.push(url);
  const img = el("img", { src: url, alt: `Photo ${n + 1}: ${file.name}` });
  img.addEventListener("error", () => { img.hidden = true; }); // a format the browser cannot draw (TIFF)
  const level = levelOf(a);
  const words = el("div", { class: "text" }, ...lines(
    el("span", {}, el("strong", {}, `Photo ${n + 1}`), " ", el("span", { class: `level ${level}` }, LEVELS[level])),
    verdict(a, level).headline,
    restsOnInWords(a),
    el("small", {}, file.name),
  ));
  li.append(img, words);
  if (locateMap && photoMarkers[n]) {
    const show = el("button", { type: "button", class: "show", "aria-label": `Show photo ${n + 1} on the map` }, "Map");
    show.addEventListener("click", () => {
      locateMap.map.setView(photoMarkers[n].getLatLng(), Math.max(locateMap.map.getZoom(), 18));
      photoMarkers[n].openPopup();
      $("map").scrollIntoView({ block: "nearest" });
    });
    li.append(show);
  }
  return li;
}

function renderSequence(res, files) {
  const placed = res.answers.filter((a) => a.estimate).length;
  const bySequence = res.answers.filter((a) => a.rests_on === "sequence").length;
  $("sequence-summary").textContent = `${res.answers.length} photos located as one path, ` +
    `${TIMES_FROM[res.times_from] || "in the order sent"}: ${placed} placed` +
    (bySequence ? ` (${bySequence} by the path through the photos around them)` : "") +
    `, ${res.answers.length - placed} without an estimate.`;
  $("sequence-note").textContent = res.note ? `${res.note[0].toUpperCase()}${res.note.slice(1)}.` : "";
  $("sequence-note").hidden = !res.note;
  drawSequence(res);
  // Answers come in the order the photos were taken; `images` says which file each one is.
  $("sequence-answers").replaceChildren(...res.answers.map((a, n) => sequenceItem(a, n, files[res.images[n]])));
  $("sequence").hidden = false;
}

// Each photo's marker is at its estimate, else at the path's place for it; the path is drawn through the
// places it holds, broken where it leaves the collection.
function drawSequence(res) {
  photoMarkers = [];
  if (!locateMap) return;
  const { map, layer } = locateMap;
  layer.clearLayers();
  const bounds = L.latLngBounds([]);
  const runs = [[]];
  res.path.forEach((q) => {
    if (q.in_collection) runs[runs.length - 1].push([q.lat, q.lon]);
    else if (runs[runs.length - 1].length) runs.push([]);
  });
  const drawn = runs.filter((r) => r.length > 1);
  drawn.forEach((r) => {
    L.polyline(r, { color: "#7b2fa8", weight: 3, className: "sequence-path", interactive: false }).addTo(layer);
    r.forEach((pt) => bounds.extend(pt));
  });
  res.answers.forEach((a, n) => {
    const est = a.estimate;
    const q = res.path[n];
    const at = est ? [est.lat, est.lon] : q.in_collection ? [q.lat, q.lon] : null;
    if (!at) return;
    if (est) {
      const circle = L.circle(at, { radius: est.radius_m, color: "#c92a2a", weight: 2, fillOpacity: 0.08 })
        .bindTooltip(textNode(`Photo ${n + 1}: within ${metres(est.radius_m)}`)).addTo(layer);
      bounds.extend(circle.getBounds());
    }
    photoMarkers[n] = L.marker(at, { icon: numberedIcon(n + 1, false), title: `Photo ${n + 1}`, alt: `Photo ${n + 1}` })
      .bindPopup(el("div", {}, ...lines(`Photo ${n + 1}`, est ? `Within ${metres(est.radius_m)}` :
        "On the most likely path (no estimate)"))).addTo(layer);
    bounds.extend(at);
  });
  const shown = photoMarkers.some((m) => m);
  // No photo placed: the collection's extent shows what it covers, as for one photo without an estimate.
  const x = !shown && res.answers.length && res.answers[0].index && res.answers[0].index.extent;
  if (x) bounds.extend(drawExtent(layer, x).getBounds());
  $("legend").hidden = !shown && !x;
  ["legend-best", "legend-others"].forEach((id) => { $(id).hidden = true; });
  $("legend-extent").hidden = !x;
  $("legend-photos").hidden = !shown;
  $("legend-path").hidden = !drawn.length;
  $("legend-est").hidden = !res.answers.some((a) => a.estimate);
  if (bounds.isValid()) map.fitBounds(bounds, { padding: [30, 30], maxZoom: 18 });
}

// -- locate: the region (the API's lat, lon and radius_m) -----------------------------------------------
// All three or none; the service checks the ranges and says what is wrong.
const REGION = [["region-lat", "lat"], ["region-lon", "lon"], ["region-radius", "radius_m"]];
function regionFields() {
  const given = REGION.map(([id, name]) => [name, $(id).value.trim()]).filter(([, v]) => v);
  if (given.length && given.length < REGION.length) {
    throw new Error("A region needs a latitude, a longitude and a radius in metres (or none of them).");
  }
  if (given.length) $("region-box").open = true;
  return Object.fromEntries(given);
}
// The region's fields, or null after saying in the locate view what is wrong with them.
function regionOrSay() {
  try {
    return regionFields();
  } catch (err) {
    status("locate", "");
    showError("locate", err.message);
    return null;
  }
}
$("region-from-map").addEventListener("click", () => {
  if (!locateMap) { showError("locate", "The map did not load: type the latitude and longitude."); return; }
  const c = locateMap.map.getCenter();
  $("region-lat").value = c.lat.toFixed(6);
  $("region-lon").value = c.lng.toFixed(6);
  if (!$("region-radius").value.trim()) $("region-radius").value = "500";
});
$("region-clear").addEventListener("click", () => REGION.forEach(([id]) => { $(id).value = ""; }));

// -- locate: the answer in words --------------------------------------------------------------------
// The level comes from the answer itself: the service gives an estimate only when a disc small enough holds
// at its stated rate (likely); reason_code no_match says no reference looks like the photo (unlike: it does
// not say the place is absent); other candidates without an estimate are possible places only (possible);
// none is no match (no features, no references).
const LEVELS = { likely: "Likely", possible: "Possible", unlike: "Unrecognised", none: "No match" };
function levelOf(res) {
  if (res.estimate) return "likely";
  if (res.reason_code === "no_match") return "unlike";
  return res.candidates.length ? "possible" : "none";
}

// The collection's extent in words (the map outlines it).
function extentInWords(res) {
  const x = res.index && res.index.extent;
  if (!x) return "";
  const size = metres(haversine({ lat: x.min_lat, lon: x.min_lon }, { lat: x.max_lat, lon: x.max_lon }));
  return ` The collection's ${res.index.size.toLocaleString("en")} references lie between ` +
    `${position(x.min_lat, x.min_lon)} and ${position(x.max_lat, x.max_lon)} (${size} across), outlined on the map.`;
}

// A rate as a count a reader pictures: 0.9 -> "9 in 10" (the answer's radius_rate; app/cli.py says it alike).
function rateInWords(rate) {
  for (const whole of [10, 20, 100]) {
    const n = Math.round(rate * whole);
    if (Math.abs(rate * whole - n) < 1e-6) return `${n} in ${whole}`;
  }
  return `${Math.round(rate * 100)} %`;
}

// How far the stated radius holds: the collection's calibrated rate when the answer states one.
function radiusInWords(est) {
  if (est.radius_rate == null) {
    return " How often the truth lies within that radius is not calibrated on this collection.";
  }
  return ` The disc is the smallest that held the truth for ${rateInWords(est.radius_rate)} of this ` +
    "collection's own answers with evidence as strong.";
}

function verdict(res, level) {
  const cands = res.candidates;
  if (level === "likely") {
    const est = res.estimate;
    const inside = cands.filter((c) => c.distance_m != null && c.distance_m <= est.radius_m).length;
    const outside = cands.filter((c) => c.distance_m != null && c.distance_m > est.radius_m);
    const nearest = outside.length ? Math.min(...outside.map((c) => c.distance_m)) : null;
    const where = `Taken within ${metres(est.radius_m)} of ${position(est.lat, est.lon)}`;
    return {
      headline: est.radius_rate == null ? `${where}.` : `${where}: ${rateInWords(est.radius_rate)} such answers are.`,
      explain: `${inside} of the ${cands.length} candidates lie ` +
        `within that radius` + (nearest == null ? "." : `; the nearest one outside it is ${metres(nearest)} away.`) +
        radiusInWords(est) + " Each candidate's distance is listed below.",
    };
  }
  if (level === "possible") {
    const best = cands[0];
    const top = cands.slice(0, 10);
    const chance = best.p_within_25m == null ? "" :
      ` The service gives it a ${Math.round(best.p_within_25m * 100)} % chance of lying within 25 m of where ` +
      "your photo was taken.";
    return {
      headline: "Possible places only: no small disc holds for evidence this strong.",
      explain: `The best match (candidate 1) is at ${position(best.lat, best.lon)}; the top ` +
        `${top.length} candidates are spread over ${metres(spread(top))}.${chance} Compare their photos ` +
        "with yours below before trusting any of them.",
    };
  }
  if (level === "unlike") {
    const best = cands[0];
    const chance = best && best.p_within_25m != null ?
      ` Even the best match has only a ${Math.round(best.p_within_25m * 100)} % chance of lying within 25 m of it.` : "";
    return {
      headline: "No reference looks like this photo.",
      explain: "None of the references looks enough like your photo to say where it was taken. This is what " +
        `was measured, not that the place is missing: a place the collection holds can look unlike its photos.${chance}` +
        `${extentInWords(res)} The closest matches are listed below for comparison.`,
    };
  }
  if (res.reason_code === "no_features") {
    return {
      headline: "This photo has nothing to recognise a place by.",
      explain: "No usable features (distinctive points) were found: it may be blank, dark or blurred. " +
        "Try a sharper photo showing buildings or streets.",
    };
  }
  const region = (res.reason || "").includes("region");
  return {
    headline: region ? "There are no references in the region searched." : "No reference could be compared with this photo.",
    explain: region ? "Search a wider region, or add references there." : "The collection holds no references yet: add some on the References tab.",
  };
}

function featuresInWords(f) {
  if (!f.extracted) return "No features (distinctive points) were found in your photo: it may be blank, dark or blurred.";
  return `Features used: ${f.kept.toLocaleString("en")} of the ${f.extracted.toLocaleString("en")} ` +
    "distinctive points found in your photo.";
}

function technical(res) {
  const rows = [
    ["Confidence", res.estimate ? `${Math.round(res.estimate.confidence * 100)} % of the candidates' weight agrees` : "no estimate"],
    ["Service's reason", res.reason ? `${res.reason_code || "?"}: ${res.reason}` : "none (an estimate)"],
    ["Search", `${res.mode}, configuration ${res.config}, ${res.index.size} references`],
    ["Time", `${Math.round(res.timings_ms.total)} ms`],
  ];
  $("tech").replaceChildren(...rows.flatMap(([k, v]) => {
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = k;
    dd.textContent = v;
    return [dt, dd];
  }));
}

function renderAnswer(res) {
  const level = levelOf(res);
  const words = verdict(res, level);
  $("level").textContent = LEVELS[level];
  $("level").className = `level ${level}`;
  $("headline").textContent = words.headline;
  $("explain").textContent = words.explain;
  // A photo without features is said so once, by the verdict.
  $("features-used").textContent = res.reason_code === "no_features" ? "" : featuresInWords(res.features);
  technical(res);
  $("answer").hidden = false;
}

// -- locate: the candidates -------------------------------------------------------------------------
function whereFrom(c, i, res) {
  const est = res.estimate;
  if (est && c.distance_m != null) {
    return `${metres(c.distance_m)} from the estimate`;
  }
  return i > 0 ? `${metres(haversine(c, res.candidates[0]))} from candidate 1` : "";
}

// The service's calibrated probability (when it gives one) that a candidate lies within 25 m of where the
// photo was taken.
function chanceInWords(c) {
  if (c.p_within_25m == null) return null;
  const p = Math.round(c.p_within_25m * 100);
  return el("span", { title: "The service's estimate of the chance that this reference lies within 25 m of where " +
    "your photo was taken" }, `${p} % chance it is within 25 m`);
}

function candidateItem(c, i, res) {
  const li = document.createElement("li");
  li.className = i === 0 ? "candidate best" : "candidate";
  const name = refName(c.reference_id, c.label);
  const img = document.createElement("img");
  img.src = `/references/${c.reference_id}/image`;
  img.alt = `Reference ${c.reference_id}${c.label ? ": " + c.label : ""}`;
  const inliers = c.inliers == null ? "" : `, ${c.inliers} matching points`;
  const file = name.file ? `${name.file} · ` : "";
  const heading = [el("strong", {}, `${i + 1}. ${name.title}`)];
  if (i === 0) heading.push(" ", el("span", { class: "tag" }, "best match"));
  const words = el("div", { class: "text" }, ...lines(
    el("span", {}, ...heading),
    whereFrom(c, i, res),
    chanceInWords(c),
    `match score ${c.score.toFixed(3)}${inliers}`,
    el("small", {}, `${file}${position(c.lat, c.lon)}`),
  ));
  li.append(img, words);
  if (locateMap) {
    const show = document.createElement("button");
    show.type = "button";
    show.className = "show";
    show.textContent = "Map";
    show.setAttribute("aria-label", `Show candidate ${i + 1} on the map`);
    show.addEventListener("click", () => focusCandidate(i));
    li.append(show);
  }
  return li;
}

function focusCandidate(i) {
  const m = candidateMarkers[i];
  locateMap.map.setView(m.getLatLng(), Math.max(locateMap.map.getZoom(), 18));
  m.openPopup();
  $("map").scrollIntoView({ block: "nearest" });
}

function renderLocate(res) {
  renderAnswer(res);
  $("candidates").replaceChildren(...res.candidates.map((c, i) => candidateItem(c, i, res)));
  drawLocate(res);
}

// Markers at one spot hide each other, and so do markers a few metres apart (24 px icons cover 11 m at
// the zoom a candidate's Map button opens, 18): each popup names the others there and those that close.
const OVERLAP_M = 12;
function sameSpot(cands, i) {
  const others = cands.map((c, j) => [j, haversine(cands[i], c)]).filter(([j]) => j !== i);
  const here = others.filter(([, d]) => d < 1).map(([j]) => j + 1);
  const near = others.filter(([, d]) => d >= 1 && d < OVERLAP_M).map(([j]) => j + 1);
  return [here.length ? `Also at this spot: ${here.join(", ")}` : "",
    near.length ? `Overlapping markers (within ${OVERLAP_M} m): ${near.join(", ")}` : ""];
}

// The collection's extent as a dashed outline (not clickable).
function drawExtent(layer, x) {
  return L.rectangle([[x.min_lat, x.min_lon], [x.max_lat, x.max_lon]],
    { color: "#1c5fa8", weight: 2, dashArray: "6 4", fill: false, interactive: false, className: "extent" })
    .addTo(layer);
}

// Marker 1 is drawn last and with the largest z-index offset, so it is on top of any later candidate at
// the same spot; the others stack by rank too.
function drawLocate(res) {
  if (!locateMap) return;
  const { map, layer } = locateMap;
  layer.clearLayers();
  const n = res.candidates.length;
  const est = res.estimate;
  $("legend").hidden = n === 0;
  ["legend-best", "legend-others"].forEach((id) => { $(id).hidden = false; });
  ["legend-photos", "legend-path"].forEach((id) => { $(id).hidden = true; });
  $("legend-est").hidden = !est;
  $("legend-extent").hidden = true;
  const bounds = L.latLngBounds(res.candidates.map((c) => [c.lat, c.lon]));
  if (est) {
    const circle = L.circle([est.lat, est.lon], { radius: est.radius_m, color: "#c92a2a", weight: 2, fillOpacity: 0.12 })
      .bindTooltip(textNode(`Estimate: within ${metres(est.radius_m)}`)).addTo(layer);
    bounds.extend(circle.getBounds());
    L.circleMarker([est.lat, est.lon], { radius: 5, color: "#c92a2a", fillOpacity: 1, className: "estimate-marker" })
      .addTo(layer);
  }
  // Without a confident estimate, the collection's extent shows what it covers (not clickable).
  const x = res.index && res.index.extent;
  if (!est && x) {
    bounds.extend(drawExtent(layer, x).getBounds());
    $("legend-extent").hidden = false;
  }
  candidateMarkers = res.candidates.map((c, i) => {
    const name = refName(c.reference_id, c.label).title;
    return L.marker([c.lat, c.lon], {
      icon: numberedIcon(i + 1, i === 0),
      zIndexOffset: i === 0 ? 100000 : (n - i) * 100,
      title: `Candidate ${i + 1}: ${name}`,
      alt: `Candidate ${i + 1}`,
      riseOnHover: true,
    }).bindPopup(el("div", {}, ...lines(`${i + 1}. ${name}`, whereFrom(c, i, res) || "best match",
      ...sameSpot(res.candidates, i))));
  });
  candidateMarkers.slice().reverse().forEach((m) => m.addTo(layer));
  if (bounds.isValid()) map.fitBounds(bounds, { padding: [30, 30], maxZoom: 18 });
}

// -- references -------------------------------------------------------------------------------------
// The count of every reference (total=true) reads every row (0.3 s at 10^6 on PostgreSQL): asked for when the
// view opens and after an add or a delete, not for every Next / Previous.
async function loadRefs(recount = true, stepped = false) {
  try {
    const count = recount || !lastPage ? "&total=true" : "";
    const page = await api(`/references?${refsCursor}&limit=${PAGE}${count}`, { headers: keyHeaders() });
    if (!count) page.total = lastPage.total;
    // A page emptied by deletes (here or elsewhere) steps once to its neighbour, the earlier one first.
    if (!page.items.length && !stepped && (page.prev_before !== null || page.next_after !== null)) {
      refsCursor = page.prev_before !== null ? `before=${page.prev_before}` : `after=${page.next_after}`;
      lastPage = page; // holds the total when this load counted: the step need not count again
      return loadRefs(false, true);
    }
    lastPage = page;
    renderRefs(page);
  } catch (e) {
    showError("refs", e.message);
  }
}

function refItem(r) {
  const li = document.createElement("li");
  li.className = "ref";
  li.dataset.id = String(r.id);
  const name = refName(r.id, r.label);
  const img = document.createElement("img");
  img.src = `/references/${r.id}/image`;
  img.alt = `Reference ${r.id}${r.label ? ": " + r.label : ""}`;
  img.loading = "lazy";
  const words = el("div", { class: "text" }, ...lines(
    el("strong", {}, name.title),
    name.file ? el("small", {}, name.file) : null,
    el("small", {}, `${position(r.lat, r.lon)} · ${r.status}`),
  ));
  const del = document.createElement("button");
  del.type = "button";
  del.textContent = "Delete";
  del.setAttribute("aria-label", `Delete reference ${r.id}`);
  del.addEventListener("click", () => deleteRef(r.id));
  li.append(img, words, del);
  return li;
}

function renderRefs(page) {
  const items = page.items;
  $("refs-count").textContent = items.length
    ? `References #${items[0].id}–#${items[items.length - 1].id} (by id), of ${page.total}`
    : page.total ? `No references on this page, of ${page.total}` : "No references yet.";
  $("prev").disabled = page.prev_before === null;
  $("next").disabled = page.next_after === null;
  $("refs").replaceChildren(...page.items.map(refItem));
  if (refsMap) {
    refsMap.layer.clearLayers();
    const pts = page.items.map((r) => [r.lat, r.lon]);
    page.items.forEach((r) => L.circleMarker([r.lat, r.lon], { radius: 5 })
      .bindTooltip(textNode(refName(r.id, r.label).title)).addTo(refsMap.layer));
    if (pts.length) refsMap.map.fitBounds(pts, { padding: [30, 30], maxZoom: 18 });
  }
}

async function deleteRef(id) {
  if (!confirm(`Delete reference ${id}? Its image, codes and metadata are removed.`)) return;
  try {
    await api(`/references/${id}`, { method: "DELETE", headers: keyHeaders() });
    showError("refs", "");
    status("refs", `Reference ${id} deleted.`);
    if ($("refs-added-item").querySelector(`li[data-id="${id}"]`)) $("refs-added").hidden = true;
    loadRefs();
  } catch (e) {
    showError("refs", e.message);
  }
}

$("prev").addEventListener("click", () => {
  if (lastPage && lastPage.prev_before !== null) { refsCursor = `before=${lastPage.prev_before}`; loadRefs(false); }
});
$("next").addEventListener("click", () => {
  if (lastPage && lastPage.next_after !== null) { refsCursor = `after=${lastPage.next_after}`; loadRefs(false); }
});

let pick = null; // the position clicked for the next reference
if (refsMap) {
  refsMap.map.on("click", (e) => {
    $("add-lat").value = e.latlng.lat.toFixed(7);
    $("add-lon").value = e.latlng.lng.toFixed(7);
    if (pick) pick.remove();
    pick = L.marker(e.latlng, { title: "New reference position" }).addTo(refsMap.map);
  });
}

// After "Add": the form is emptied (the next reference starts from nothing), the reference is shown above
// the list whatever page it falls on, and the list moves to the page that holds a new one (the last: ids
// grow) with it marked there.
function clearAddForm() {
  $("add-form").reset();
  if (pick) { pick.remove(); pick = null; }
}

async function showAdded(id, duplicate) {
  const ref = await api(`/references/${id}`, { headers: keyHeaders() });
  $("refs-added-title").textContent = duplicate ? `Already stored as reference ${id}:` : `Just added (reference ${id}):`;
  const item = refItem(ref);
  item.classList.add("added");
  $("refs-added-item").replaceChildren(item);
  $("refs-added").hidden = false;
  if (!duplicate) {
    refsCursor = LAST_PAGE;
  }
  await loadRefs();
  const listed = document.querySelector(`#refs li[data-id="${id}"]`);
  if (listed) listed.classList.add("added");
  if (refsMap) refsMap.map.setView([ref.lat, ref.lon], Math.max(refsMap.map.getZoom(), 17));
  $("refs-added").scrollIntoView({ block: "nearest" });
}

$("add-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const file = $("add-file").files[0];
  if (!file) { showError("refs", "Choose an image to add."); return; }
  const form = new FormData();
  form.append("image", file);
  for (const [id, name] of [["add-lat", "lat"], ["add-lon", "lon"], ["add-label", "label"]]) {
    if ($(id).value.trim()) form.append(name, $(id).value.trim());
  }
  showError("refs", "");
  try {
    const res = await api("/references", { method: "POST", body: form, headers: keyHeaders() });
    status("refs", res.duplicates[0] ? `Already stored as reference ${res.reference_ids[0]}.`
                                     : `Accepted as reference ${res.reference_ids[0]}; encoding…`);
    clearAddForm();
    await waitJob(res.job_id);
    // A duplicate uploaded with other metadata keeps the stored one: the service says so in `notes`.
    if (res.notes && res.notes.length) status("refs", `${$("refs-status").textContent} ${res.notes.join(" ")}`);
    await showAdded(res.reference_ids[0], res.duplicates[0]);
  } catch (err) {
    showError("refs", err.message);
  }
});

async function waitJob(id) {
  for (let i = 0; i < 120; i++) {
    const job = await api(`/jobs/${id}`, { headers: keyHeaders() });
    if (job.status === "done" || job.status === "failed") {
      status("refs", job.status === "done" ? "Reference indexed." : `Encoding failed: ${job.items[0].error}`);
      return job;
    }
    await new Promise((r) => setTimeout(r, 500));
  }
}

// The Library page links to the References view as /#references.
if (location.hash === "#references") select("tab-refs");
