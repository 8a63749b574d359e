// The HMI's pages: one document, pages by the URL's hash, live updates over one websocket.
"use strict";

const S = { me: null, status: null, statusAt: 0, liveJob: null, view: null, scanStart: null, designs: [], lastResult: null };
const $ = (id) => document.getElementById(id);
const esc = (s) => String(s == null ? "" : s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
const fmt = (v, d = 2) => (v == null || !isFinite(v) ? "-" : Number(v).toFixed(d));
const FINAL = ["done", "failed", "aborted", "interrupted", "cancelled"];
// a message may name files on the cell's server: show their names, never the server's paths
const noPaths = (m) => String(m == null ? "" : m).replace(/(^|[\s'"(=])((?:\/[^\s'"():,;]+){2,})/g, (_, pre, p) => pre + p.split("/").pop());

// ------------------------------------------------------------------ confirmation (once, in the page)
function askConfirm(text, yes) {
  return new Promise((resolve) => {
    $("confirm-text").textContent = text;
    $("confirm-yes").textContent = yes;
    $("confirm").classList.remove("hidden");
    const done = (v) => { $("confirm").classList.add("hidden"); $("confirm-yes").onclick = null; $("confirm-no").onclick = null; resolve(v); };
    $("confirm-yes").onclick = () => done(true);
    $("confirm-no").onclick = () => done(false);
    $("confirm-no").focus();
  });
}

async function api(method, path, body) {
  const headers = {};
  if (method !== "GET") { headers["Content-Type"] = "application/json"; if (S.me) headers["X-CSRF-Token"] = S.me.csrf; }
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body), credentials: "same-origin" });
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  if (r.status === 401 && path !== "/api/login") showLogin();
  return { ok: r.ok, status: r.status, data };
}
const errText = (res) => (res.data && res.data.message ? (res.data.field ? res.data.field + ": " : "") + res.data.message : "error " + res.status);

// ------------------------------------------------------------------ log-in
function showLogin() { $("app").classList.add("hidden"); $("login").classList.remove("hidden"); $("login-user").focus(); }
async function afterLogin(me) {
  S.me = me;
  $("login").classList.add("hidden"); $("app").classList.remove("hidden");
  $("who").textContent = `${me.user} (${me.role})`;
  document.body.dataset.role = me.role;
  for (const el of document.querySelectorAll(".operator-only")) el.classList.toggle("hidden", !me.may.includes("pause"));
  for (const el of document.querySelectorAll(".engineer-only")) el.dataset.allowed = me.may.includes("reset") ? "1" : "";
  $("nav-start").classList.toggle("hidden", !me.may.includes("trigger"));
  connect();
  route();
  refreshVerdicts();
}
// the verdicts of ended jobs (the history index): the state publication carries none
async function refreshVerdicts() {
  const res = await api("GET", "/api/jobs");
  if (!res.ok) return;
  S.verdicts = Object.fromEntries(res.data.jobs.map((j) => [j.job_id, j.verdict]));
  if (S.status) renderCell(S.status);
}
$("login-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  $("login-error").textContent = "";
  const res = await api("POST", "/api/login", { user: $("login-user").value, password: $("login-password").value });
  $("login-password").value = "";
  if (res.ok) afterLogin(res.data); else $("login-error").textContent = errText(res);
});
$("logout").addEventListener("click", async () => { await api("POST", "/api/logout", {}); S.me = null; if (S.ws) S.ws.close(); showLogin(); });

// ------------------------------------------------------------------ live updates
function connect() {
  if (S.ws && S.ws.readyState <= 1) return;
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  S.ws = ws;
  ws.onopen = () => $("conn").classList.add("up");
  ws.onclose = (e) => {
    $("conn").classList.remove("up");
    if (e.code === 4401) { S.me = null; showLogin(); return; } // the session ended (log-out elsewhere, expiry)
    if (S.me) setTimeout(connect, 1000);
  };
  ws.onmessage = (m) => {
    const ev = JSON.parse(m.data);
    if (ev.type === "status") onStatus(ev.status, ev.t_server_ms);
    else if (ev.type === "live") onLive(ev);
    else if (ev.type === "history" || ev.type === "report") onJobEnd(ev);
  };
}
setInterval(() => { if (S.me) renderBanner(); }, 1000);

// ------------------------------------------------------------------ pages
const PAGES = ["cell", "start", "scan", "result", "history"];
function route() {
  const [page, arg] = (location.hash.replace(/^#/, "") || "cell").split("/");
  let p = PAGES.includes(page) ? page : "cell";
  if (p === "start" && !(S.me && S.me.may.includes("trigger"))) { p = "cell"; history.replaceState(null, "", "#cell"); } // not offered
  for (const name of PAGES) $("page-" + name).classList.toggle("active", name === p);
  for (const a of document.querySelectorAll("nav a")) a.classList.toggle("active", a.dataset.page === p);
  document.body.dataset.page = p;
  if (p === "start") loadStart();
  if (p === "result") loadResult(arg ? decodeURIComponent(arg) : null);
  if (p === "history") loadHistory(arg ? decodeURIComponent(arg) : null);
  if (p === "scan") loadScan();
}
window.addEventListener("hashchange", () => { if (S.me) route(); });

// ------------------------------------------------------------------ Cell page and banner
function onStatus(st, tServer) {
  S.status = st; S.statusAt = Date.now();
  document.body.dataset.cellState = st.state;
  renderCell(st);
  const resetable = ["faulted", "emergency_stopped"].includes(st.state);
  $("btn-reset").classList.toggle("hidden", !(resetable && $("btn-reset").dataset.allowed));
  renderBanner();
  renderHealth();
  if (document.body.dataset.page === "scan") renderScan();
  // publication -> on screen (same clock on one machine; kept for benchmarks/hmi.py)
  S.statusLatencyMs = (S.statusLatencyMs || []).slice(-999).concat([Date.now() - Date.parse(st.t_utc)]);
  document.body.dataset.statusT = st.t_utc;
}
const jobWords = (j) => esc(j.state.replace(/_/g, " ")) + (j.stage && j.stage !== j.state ? ": " + esc(j.stage) : "");
const verdictOf = (id) => (S.verdicts || {})[id] || null;
function renderCell(st) {
  $("cell-state").textContent = st.state.replace("_", " ");
  $("cell-message").textContent = noPaths(st.message);
  const j = st.job, active = j && !FINAL.includes(j.state);
  // the job holding the robot; once it ended, the last job, said so (never "idle" beside "in progress")
  $("cell-job-label").textContent = !j || active ? "Job in progress" : "Last job";
  const v = j && !active ? verdictOf(j.job_id) : null;
  $("cell-job").innerHTML = j ? `<b>${esc(j.plate_id)}</b> <small>${esc(j.job_id)}</small><br>${jobWords(j)}${v ? ` · <span class="verdict-word ${esc(v)}">${esc(v.toUpperCase())}</span>` : ""}` : "none";
  $("cell-job-bar").parentElement.classList.toggle("hidden", !active);
  $("cell-job-bar").style.width = active ? (100 * j.fraction).toFixed(1) + "%" : "0";
  $("cell-queue").innerHTML = st.queue.map((q) => `<div>${q.position}. <b>${esc(q.plate_id)}</b> <small>${esc(q.job_id)}</small></div>`).join("") || "<div class=\"none\">empty</div>";
  $("cell-analyses").innerHTML = st.analyses.map((a) => `<li>${esc(a.plate_id)}: ${esc(a.state)} ${esc(a.worker_id || "")}</li>`).join("") || "<li>none</li>";
  $("cell-workers").innerHTML = (st.workers.map((w) => `<li>${esc(w)}</li>`).join("") || "<li>no worker: reports wait</li>")
    + (st.workers_refused || []).map((w) => `<li class="bad">not given jobs: ${esc(w)}</li>`).join("");
  $("cell-recent").innerHTML = "<tr><th>plate</th><th>job</th><th>state</th><th>verdict</th><th>message</th><th></th></tr>" +
    st.recent.slice().reverse().map((r) => { const rv = verdictOf(r.job_id); return `<tr class="clickable ${rv === "fail" ? "fail" : ""}" data-job="${esc(r.job_id)}"><td>${esc(r.plate_id)}</td><td>${esc(r.job_id)}</td><td>${esc(r.state)}</td><td>${rv ? esc(rv.toUpperCase()) : "-"}</td><td>${esc(noPaths(r.message))}</td><td>${
      ["interrupted", "failed"].includes(r.state) && S.me && S.me.may.includes("reanalyse") ? `<button class="reanalyse" data-job="${esc(r.job_id)}">Re-analyse</button>` : ""}</td></tr>`; }).join("") + (st.recent.length ? "" : `<tr><td colspan="6" class="none">none yet</td></tr>`);
}
function renderHealth() {
  const age = S.statusAt ? (Date.now() - S.statusAt) / 1000 : Infinity;
  const items = [
    [age < 3.5, age < 3.5 ? "daemon: publishing" : "daemon: no state for " + (isFinite(age) ? age.toFixed(0) + " s" : "ever")],
    [S.status && S.status.workers.length > 0, `analysis workers: ${S.status ? S.status.workers.length : 0}`],
    [S.status && S.status.state !== "emergency_stopped" && S.status.state !== "faulted", "robot: " + (S.status ? (S.status.state === "emergency_stopped" ? "e-stopped" : S.status.state === "faulted" ? "faulted" : "ok") : "?")],
    [S.status && !(S.status.job && S.status.job.state === "scanning" && S.status.job.profiles === 0 && S.status.job.fraction > 0.1), "sensor: " + (S.status && S.status.job ? S.status.job.profiles + " profiles" : "idle")],
  ];
  $("cell-health").innerHTML = items.map(([ok, t]) => `<li style="color:${ok ? "#8f8" : "#f88"}">${esc(t)}</li>`).join("");
}
function renderBanner() {
  const b = $("banner"), st = S.status;
  const age = S.statusAt ? (Date.now() - S.statusAt) / 1000 : 0;
  let html = "", warn = false;
  if (st && st.state === "emergency_stopped") {
    html = `<h2>EMERGENCY STOP</h2>${esc(st.message)}<ol>
      <li>Make the cell safe; find out why the stop was pressed.</li>
      <li>Release the e-stop and reset it on the controller (motors off or on).</li>
      <li>An engineer presses <b>Reset cell</b> on the Cell page (refused while the controller still reports the e-stop).</li>
      <li>Re-analyse the interrupted job from its raw data (Cell page, Recent jobs), or start the plate again.</li></ol>`;
  } else if (st && st.state === "faulted") {
    warn = true;
    html = `<h2>FAULT</h2>${esc(st.message)}<ol><li>Check the robot and the sensor (the job's raw data is kept).</li>
      <li>An engineer presses <b>Reset cell</b>, or start the plate again (a new scan is accepted).</li></ol>`;
  } else if (S.statusAt && age > 5) {
    warn = true;
    html = `<h2>NO CONTACT WITH THE CELL</h2>No state from the daemon for ${age.toFixed(0)} s: is <code>cellctl run</code> running? The page updates by itself when it is back.`;
  }
  b.innerHTML = html; b.classList.toggle("hidden", !html); b.classList.toggle("warn", warn);
  b.dataset.state = st ? st.state : "";
}
$("btn-reset").addEventListener("click", async () => {
  const res = await api("POST", "/api/control/reset", {});
  $("cell-message").textContent = res.ok ? "reset: cell " + res.data.state : "reset refused: " + errText(res);
});
$("cell-recent").addEventListener("click", async (e) => {
  const btn = e.target.closest("button.reanalyse");
  if (btn) {
    const res = await api("POST", "/api/control/reanalyse", { job_id: btn.dataset.job });
    $("cell-message").textContent = res.ok ? "re-analysing " + btn.dataset.job : "re-analyse refused: " + errText(res);
    return;
  }
  const tr = e.target.closest("tr[data-job]");
  if (tr) location.hash = "#result/" + encodeURIComponent(tr.dataset.job);
});

// ------------------------------------------------------------------ Start page
async function loadStart() {
  const res = await api("GET", "/api/designs");
  if (!res.ok) return;
  S.designs = res.data.designs;
  const sel = $("start-design"), keep = sel.value;
  sel.innerHTML = S.designs.map((d) => `<option>${esc(d)}</option>`).join("");
  if (keep && S.designs.includes(keep)) sel.value = keep;
  const p = res.data.default_placement;
  if (p && $("start-x").value === "") { $("start-x").value = p.pos_mm[0]; $("start-y").value = p.pos_mm[1]; $("start-z").value = p.pos_mm[2]; $("start-yaw").value = p.rpy_deg[2]; }
  preview();
  $("start-plate").focus();
}
async function preview() {
  const d = $("start-design").value;
  if (!d) return;
  const res = await api("GET", "/api/designs/preview?path=" + encodeURIComponent(d));
  if (!res.ok) { $("start-preview-info").textContent = errText(res); return; }
  const xyz = new Float32Array(res.data.xyz_mm.flat());
  if (!S.previewView) S.previewView = PointView($("start-preview"), { top: true });
  S.previewView.setPoints(xyz, heightColours(xyz, res.data.min_mm[2], res.data.max_mm[2]));
  const size = res.data.max_mm.map((v, k) => v - res.data.min_mm[k]);
  $("start-preview-info").textContent = `${size[0].toFixed(0)} x ${size[1].toFixed(0)} mm, height ${size[2].toFixed(0)} mm`;
}
$("start-design").addEventListener("change", preview);
$("start-locate").addEventListener("change", () => {
  for (const id of ["start-x", "start-y", "start-z", "start-yaw"]) {
    $(id).disabled = $("start-locate").checked; $(id).required = !$("start-locate").checked;
  }
});
$("start-plate").addEventListener("keydown", (e) => { if (e.key === "Enter") { e.preventDefault(); $("start-design").focus(); } }); // a barcode scanner ends with Enter
$("start-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  $("start-error").textContent = ""; $("start-ok").textContent = "";
  const num = (id) => Number($(id).value);
  const body = { plate_id: $("start-plate").value.trim(), design: $("start-design").value, note: $("start-note").value };
  // without a placement the cell finds the plate (a locate run); with one, the locate run checks it
  if (!$("start-locate").checked)
    body.placement = { pos_mm: [num("start-x"), num("start-y"), num("start-z")], rpy_deg: [0, 0, num("start-yaw")] };
  const busy = plateBusy(body.plate_id);
  if (busy && !(await askConfirm(`Plate ${body.plate_id} is already ${busy}. Start another scan of it?`, "Start another scan"))) {
    $("start-error").textContent = "Not started."; return;
  }
  $("start-submit").disabled = true;
  const res = await api("POST", "/api/trigger", body);
  $("start-submit").disabled = false;
  if (!res.ok) { $("start-error").textContent = "Not started. " + errText(res); return; }
  $("start-plate").value = ""; $("start-note").value = ""; // a second press must not scan the same plate again
  $("start-ok").textContent = res.data.state === "queued" ? `Queued at position ${res.data.queue_position} (job ${res.data.job_id})` : `Started: job ${res.data.job_id}`;
  S.followJob = res.data.job_id;
  location.hash = "#scan";
});

// where the plate already is in the cell: "being scanned (job ...)", "queued (position 2)", or null
function plateBusy(plate) {
  const st = S.status;
  if (!st) return null;
  if (st.job && st.job.plate_id === plate && !FINAL.includes(st.job.state)) return `${st.job.state.replace(/_/g, " ")} (job ${st.job.job_id})`;
  const q = st.queue.find((x) => x.plate_id === plate);
  return q ? `queued (position ${q.position}, job ${q.job_id})` : null;
}

// ------------------------------------------------------------------ Scan page
function scanJob() {
  const st = S.status;
  if (!st || !st.job) return null;
  return st.job;
}
function loadScan() {
  if (!S.view) S.view = PointView($("scan-view"));
  renderScan();
}
// the live view shows one job: a new job starts from an empty view, then the cloud so far (a page
// opened or reloaded mid-scan), then the chunks that arrived meanwhile (those after the cloud's seq)
async function loadLive(jobId) {
  if (!S.view) S.view = PointView($("scan-view"));
  S.liveJob = jobId; S.zRange = null; S.liveBuffer = []; S.liveLoading = jobId;
  S.view.setPoints(new Float32Array(0), new Uint8Array(0));
  S.livePoints = 0; $("scan-points").textContent = "0 points"; $("scan-points").dataset.points = "0";
  const res = await api("GET", "/api/jobs/" + encodeURIComponent(jobId) + "/live");
  if (S.liveJob !== jobId) return; // another job began meanwhile
  const seq = res.ok ? res.data.seq : -1;
  if (res.ok && res.data.xyz_mm.length) addLive(res.data.xyz_mm);
  const later = S.liveBuffer; S.liveBuffer = null; S.liveLoading = null;
  for (const ev of later) if (ev.seq > seq && ev.xyz_mm.length) addLive(ev.xyz_mm);
}
function addLive(pts) {
  const xyz = new Float32Array(pts.flat());
  if (S.zRange == null) { let lo = Infinity, hi = -Infinity; for (let i = 2; i < xyz.length; i += 3) { lo = Math.min(lo, xyz[i]); hi = Math.max(hi, xyz[i]); } S.zRange = [lo, hi + 1]; }
  S.view.addPoints(xyz, heightColours(xyz, S.zRange[0], S.zRange[1]));
  S.livePoints = S.view.count();
  S.liveUpdates = (S.liveUpdates || 0) + 1;
  $("scan-points").textContent = `${S.livePoints} points`;
  $("scan-points").dataset.points = String(S.livePoints);
}
function onLive(ev) {
  if (ev.job_id !== S.liveJob) loadLive(ev.job_id);
  if (S.liveLoading === ev.job_id) { S.liveBuffer.push(ev); return; }
  if (ev.xyz_mm.length) addLive(ev.xyz_mm);
}
// the job the Scan page watches: when it ends the page says how (aborted, failed, ...) and a done
// job leads to its result once indexed, whether it was started here or the page was (re)opened
function watchScan(j) {
  const st = S.status, w = S.watchJob;
  if (w && (!j || j.job_id !== w || FINAL.includes(j.state))) {
    const ended = [...st.recent, ...(st.job ? [st.job] : [])].find((x) => x.job_id === w && FINAL.includes(x.state));
    if (ended || (j && j.job_id !== w)) {
      S.watchJob = null;
      if (ended && ended.state === "done") S.followJob = w;
      else if (ended) $("scan-notice").textContent = `Plate ${ended.plate_id} · job ${ended.job_id} ${ended.state}${ended.message ? ": " + noPaths(ended.message) : ""}`;
    }
  }
  if (j && !FINAL.includes(j.state) && S.watchJob !== j.job_id) { S.watchJob = j.job_id; }
}
function renderScan() {
  const j = scanJob();
  renderMotion(j);
  if (j && j.job_id !== S.liveJob && !FINAL.includes(j.state)) loadLive(j.job_id); // a new job: not the last plate's cloud
  if (document.body.dataset.page === "scan") watchScan(j);
  if (!j) { $("scan-job").textContent = "no scan in progress"; return; }
  $("scan-job").innerHTML = `<b>${esc(j.plate_id)}</b> ${esc(j.job_id)}<br>${jobWords(j)} ${esc(noPaths(j.message))}`;
  $("scan-job").title = `${j.plate_id} ${j.job_id}: ${j.state} ${j.stage} ${noPaths(j.message)}`;
  const m = /\((\d+)\/(\d+)\)/.exec(j.stage || "");
  $("scan-pass").textContent = m ? `${m[1]} / ${m[2]}` : "-";
  const f = j.fraction || 0;
  $("scan-bar").style.width = (100 * f).toFixed(1) + "%";
  $("scan-progress").textContent = `${(100 * f).toFixed(0)} %  ·  ${j.profiles} profiles`;
  $("scan-progress").dataset.fraction = String(f);
  if (["scanning", "paused"].includes(j.state)) {
    if (!S.scanStart || S.scanStart.job !== j.job_id) S.scanStart = { job: j.job_id, t: Date.now(), f };
    // a pause stops the clock the estimate runs on: time left holds still instead of rising
    if (j.state === "paused") { if (!S.scanStart.pausedAt) S.scanStart.pausedAt = Date.now(); }
    else if (S.scanStart.pausedAt) { S.scanStart.t += Date.now() - S.scanStart.pausedAt; S.scanStart.pausedAt = null; }
    const now = S.scanStart.pausedAt || Date.now();
    const el = (now - S.scanStart.t) / 1000, df = f - S.scanStart.f;
    const left = df > 0.02 ? Math.max(0, (el * (1 - f)) / df).toFixed(0) + " s" : "…";
    $("scan-left").textContent = j.state === "paused" ? left + " (paused)" : left;
  } else $("scan-left").textContent = ["done", "waiting_for_worker", "analysing"].includes(j.state) ? "scan done" : "-";
  $("btn-pause").disabled = j.state !== "scanning";
  $("btn-resume").disabled = j.state !== "paused";
  $("btn-abort").disabled = !["planning", "scanning", "paused"].includes(j.state);
}
// the motion process's counters for the job (JobProgress.motion), when the cell publishes them
function renderMotion(j) {
  const m = j && j.motion, el = $("scan-motion");
  el.classList.toggle("hidden", !m);
  if (!m) return;
  el.innerHTML = `<span class="label">Motion</span> <span data-k="stale">${m.egm_stale_cycles} stale cycle${m.egm_stale_cycles === 1 ? "" : "s"}</span> · <span data-k="lost">${m.egm_lost_cycles} lost cycle${m.egm_lost_cycles === 1 ? "" : "s"}</span> · <span data-k="p99">reply p99 ${m.egm_reply_p99_us == null ? "-" : fmt(m.egm_reply_p99_us, 0) + " µs"}</span> · <span data-k="track">max tracking error ${fmt(m.max_tracking_error_mm, 2)} mm${m.max_tracking_t_traj_s == null ? "" : " at " + fmt(m.max_tracking_t_traj_s, 1) + " s"}</span>`;
  el.classList.toggle("warn", m.egm_stale_cycles > 0 || m.egm_lost_cycles > 0);
}
for (const action of ["pause", "resume", "abort"]) {
  $("btn-" + action).addEventListener("click", async () => {
    const j = scanJob();
    if (action === "abort" && !(await askConfirm(j ? `Abort the scan of plate ${j.plate_id} (job ${j.job_id})? The robot stops and the scan is lost.` : "Abort?", "Abort scan"))) return;
    const res = await api("POST", "/api/control/" + action, j ? { job_id: j.job_id } : {});
    $("scan-error").textContent = res.ok ? "" : action + " refused: " + errText(res);
    if (res.ok && action === "abort" && j) $("scan-notice").textContent = `Plate ${j.plate_id} · job ${j.job_id} ${res.data.job_state || "aborted"}`;
  });
}
function onJobEnd(ev) {
  if (ev.type === "history") refreshVerdicts();
  if (ev.type === "history" && S.followJob === ev.job_id) {
    S.followJob = null;
    if (["scan", "start"].includes(document.body.dataset.page)) location.hash = "#result/" + encodeURIComponent(ev.job_id);
  }
  else if (document.body.dataset.page === "history") loadHistory(S.historyPlate);
}

// ------------------------------------------------------------------ Result page
async function loadResult(jobId) {
  if (!jobId) {
    const res = await api("GET", "/api/jobs");
    const done = res.ok ? res.data.jobs.find((j) => j.verdict) : null;
    if (!done) { $("result-title").textContent = "No result yet"; return; }
    jobId = done.job_id;
  }
  const res = await api("GET", "/api/jobs/" + encodeURIComponent(jobId));
  if (!res.ok) { $("result-title").textContent = errText(res); return; }
  const { job, report, files, previous } = res.data, plan = res.data.heating_plan;
  document.body.dataset.resultJob = job.job_id;
  $("result-title").textContent = `Plate ${job.plate_id} · job ${job.job_id}`;
  $("result-meta").innerHTML = `state ${esc(job.state)} · design ${esc(job.design)} · ${esc(job.created_utc)}<br>${esc(noPaths((job.history.slice(-1)[0] || {}).message || ""))}`;
  $("result-downloads").innerHTML = files.map((f) => `<a href="/api/jobs/${encodeURIComponent(job.job_id)}/files/${f}" download>${esc(f)}</a>`).join("");
  const rb = $("btn-reanalyse");
  rb.classList.toggle("hidden", !(rb.dataset.allowed && ["interrupted", "failed"].includes(job.state)));
  rb.dataset.job = job.job_id;
  const v = $("result-verdict");
  v.className = "verdict" + (report ? " " + report.verdict : "");
  v.textContent = report ? report.verdict.toUpperCase() : job.state.toUpperCase();
  // a job without a report (aborted, failed, not analysed yet): no empty views, the reason in words
  for (const id of ["result-views", "result-lines-tile", "result-rework-tile", "result-plots-tile"]) $(id).classList.toggle("hidden", !report);
  renderHeatingPlan(plan);
  if (!report) { $("result-lines").innerHTML = ""; $("result-plots").innerHTML = ""; $("result-rework").innerHTML = ""; return; }
  const tol = report.tolerances, stdMm = tol.deviation_standard_mm, limMm = tol.deviation_limit_mm;
  const prev = previous ? Object.fromEntries(previous.lines.map((l) => [l.name, l])) : {};
  const lname = (l) => l.name || `${l.family[0].toUpperCase()}${l.index}`;
  const predicted = plan && plan.predicted ? plan.predicted.zmax_mm : null;
  $("result-lines").innerHTML = `<tr><th>line</th><th>pos mm</th><th>Sz avg mm</th><th>Zmax mm</th><th>at mm</th><th>CI</th><th>Sc avg 1/mm</th><th>Cmax 1/mm</th><th>length mm</th><th>grade</th><th>result</th>${previous ? "<th>prev. Zmax</th>" : ""}${predicted ? "<th>Zmax after heating (predicted)</th>" : ""}</tr>` +
    report.lines.map((l) => `<tr class="${l.pass ? "" : "fail"}" data-line="${esc(lname(l))}"><td>${esc(lname(l))} ${esc(l.family)}</td><td>${fmt(l.position_mm, 0)}</td><td>${fmt(l.sz_avg_mm)}</td><td>${fmt(l.zmax_mm)}</td><td>${fmt(l.zmax_at_mm, 0)}</td><td>${fmt(l.ci, 3)}</td><td>${Number(l.sc_avg_per_mm).toExponential(2)}</td><td>${Number(l.cmax_per_mm).toExponential(2)}</td><td>${fmt(l.length_mm, 0)}</td><td>${esc(l.grade)}</td><td>${l.pass ? "pass" : "FAIL"}</td>${previous ? `<td>${prev[lname(l)] ? fmt(prev[lname(l)].zmax_mm) : "-"}</td>` : ""}${predicted ? `<td>${predicted[lname(l)] == null ? "-" : fmt(predicted[lname(l)])}</td>` : ""}</tr>`).join("");
  $("result-legend").innerHTML = `<span style="background:rgb(${BAND.std})">|d| ≤ ${stdMm} mm</span><span style="background:rgb(${BAND.limit})">≤ ${limMm} mm</span><span style="background:rgb(${BAND.out})">&gt; ${limMm} mm</span>`;
  const mres = await api("GET", "/api/jobs/" + encodeURIComponent(job.job_id) + "/map");
  const map = mres.ok ? mres.data : null;
  if (map) {
    // the map is a raster of cell means (the server bounds its cells whatever the plate's size):
    // the 3D view shows one point per cell that holds data, at the cell's centre
    const { nx, ny, cell_mm: cm } = map, dm = map.deviation_mm;
    const m = dm.reduce((n, v) => n + (v === null ? 0 : 1), 0);
    const d3 = new Float32Array(3 * m), col = new Uint8Array(3 * m);
    let amax = 1e-3, p = 0;
    for (let k = 0; k < nx * ny; k++) {
      const v = dm[k];
      if (v === null) continue;
      amax = Math.max(amax, Math.abs(v));
      d3[3 * p] = (Math.floor(k / ny) + 0.5) * cm; d3[3 * p + 1] = ((k % ny) + 0.5) * cm; d3[3 * p + 2] = v;
      col.set(bandColour(v, stdMm, limMm), 3 * p); p++;
    }
    if (!S.res3d) S.res3d = PointView($("result-3d"));
    S.res3d.setZScale(0.15 * Math.max(...report.plate_size_mm) / amax);
    S.res3d.setPoints(d3, col);
  }
  // rework regions: runs beyond the limit along each line, placed in the plate frame (mm from the
  // reference corner); the deviation is design minus plate: > 0, the plate lies below the design
  const rework = [], regions = [];
  $("result-plots").innerHTML = "";
  report.lines.forEach((l, k) => {
    const ld = map && map.lines[k];
    const c = document.createElement("canvas"); c.width = 370; c.height = 170; c.dataset.line = lname(l);
    $("result-plots").appendChild(c);
    if (ld) plotLine(c, lname(l), ld.s_mm, ld.deviation_mm, stdMm, limMm, l.pass);
    if (!ld || l.pass) return;
    const s = ld.s_mm, dv = ld.deviation_mm, s0 = s[0], s1 = s[s.length - 1];
    const pos = (sv) => {
      if (!l.start_plate_mm || !l.end_plate_mm) return null;
      const t = (sv - s0) / Math.max(s1 - s0, 1e-9);
      return l.start_plate_mm.map((a, j) => a + t * (l.end_plate_mm[j] - a));
    };
    const at = (sv) => { const p = pos(sv); return p ? `(${p[0].toFixed(0)}, ${p[1].toFixed(0)}) mm` : `s = ${sv.toFixed(0)} mm along the line`; };
    let i = 0, found = 0;
    while (i < s.length) {
      if (Math.abs(dv[i]) <= limMm) { i++; continue; }
      let j = i, worst = 0;
      while (j < s.length && Math.abs(dv[j]) > limMm) { if (Math.abs(dv[j]) > Math.abs(worst)) worst = dv[j]; j++; }
      const no = regions.length + 1;
      regions.push({ no, p0: pos(s[i]), p1: pos(s[j - 1]), worst });
      rework.push(`<li data-region="${no}"><b>${no}</b> line ${esc(lname(l))}: from ${at(s[i])} to ${at(s[j - 1])}: ${reworkWords(worst)}</li>`);
      found++; i = j;
    }
    if (!found) rework.push(`<li>line ${esc(lname(l))}: Zmax ${fmt(l.zmax_mm)} mm at ${fmt(l.zmax_at_mm, 0)} mm along the line</li>`);
  });
  $("result-rework").innerHTML = rework.join("") || "<li>none: every line within the limit</li>";
  if (map) drawPlateMap($("result-top"), map, report, regions, stdMm, limMm, lname, plan);
}
// the heating plan (heating-plan.json, made by the cell after the report): one sentence a line in
// the crew's order, the predicted after-state, the planner's notes; or why there is none
function renderHeatingPlan(plan) {
  $("result-heating-tile").classList.toggle("hidden", !plan);
  if (!plan) { $("result-heating").innerHTML = ""; $("result-heating-meta").textContent = ""; return; }
  const p = plan.predicted;
  const after = p ? `predicted after this round: verdict ${esc(p.verdict.toUpperCase())}, RMS ${fmt(p.rms_before_mm)} → ${fmt(p.rms_after_mm)} mm` : "";
  $("result-heating-meta").innerHTML = plan.status === "plan"
    ? [after, ...(plan.notes || []).map(esc)].filter(Boolean).join("<br>")
    : `no heating plan: ${esc(noPaths(plan.reason || ""))}`;
  $("result-heating").innerHTML = plan.lines.map((l) => `<li data-heat="${esc(l.id)}" class="face-${esc(l.face)}">${esc(l.sentence)} · ${fmt(l.heat_input_j_mm, 0)} J/mm, bend ${fmt(l.bend_deg)}°</li>`).join("");
}
// which way the plate must go, in the words of the shop floor (d = design - plate)
const reworkWords = (worst) => (worst > 0
  ? `the plate lies ${worst.toFixed(2)} mm below the design here: it must come up`
  : `the plate lies ${(-worst).toFixed(2)} mm above the design here: it must come down`);

// the top view in the plate frame: mm from the reference corner (origin bottom left, x to the
// right, y up), the deviation coloured by band, the detection lines drawn and named, the rework
// regions numbered as in the list
function drawPlateMap(c, map, report, regions, stdMm, limMm, lname, plan) {
  const [lx, ly] = map.plate_size_mm, g = c.getContext("2d"), W = c.width, H = c.height;
  const L = 52, B = 36, T = 26, R = 40, k = Math.min((W - L - R) / lx, (H - T - B) / ly);
  const X = (x) => L + x * k, Y = (y) => H - B - y * k;
  g.fillStyle = "#06090b"; g.fillRect(0, 0, W, H);
  g.strokeStyle = "#3a4a5a"; g.lineWidth = 1; g.strokeRect(X(0), Y(ly), lx * k, ly * k);
  // the raster: one pixel per cell on a canvas of its own, scaled onto the plate's rectangle
  const { nx, ny, cell_mm: cm } = map, img = new ImageData(nx, ny);
  let cells = 0;
  map.deviation_mm.forEach((v, q) => {
    if (v === null) return;
    const o = 4 * ((ny - 1 - (q % ny)) * nx + Math.floor(q / ny)); // row 0 at the top: y up on screen
    img.data.set(bandColour(v, stdMm, limMm), o); img.data[o + 3] = 255; cells++;
  });
  const raster = document.createElement("canvas"); raster.width = nx; raster.height = ny;
  raster.getContext("2d").putImageData(img, 0, 0);
  g.save(); g.beginPath(); g.rect(X(0), Y(ly), lx * k, ly * k); g.clip(); // the last cells may pass the edge
  g.imageSmoothingEnabled = false; g.drawImage(raster, X(0), Y(ny * cm), nx * cm * k, ny * cm * k); g.restore();
  c.dataset.cells = String(cells);
  // axes in mm
  g.font = "13px system-ui"; g.fillStyle = "#9fb0bf";
  const xs = niceStep(lx, Math.max(2, Math.floor((lx * k) / 80))), ys = niceStep(ly, Math.max(2, Math.floor((ly * k) / 50)));
  g.textAlign = "center";
  for (let v = 0; v <= lx + 1e-6; v += xs) { g.fillRect(X(v), Y(0), 1, 5); g.fillText(tickText(v, xs), X(v), Y(0) + 18); }
  g.fillText("x mm", X(lx / 2), H - 3);
  g.textAlign = "right";
  for (let v = 0; v <= ly + 1e-6; v += ys) { g.fillRect(X(0) - 5, Y(v), 5, 1); g.fillText(tickText(v, ys), X(0) - 7, Y(v) + 4); }
  g.save(); g.translate(12, Y(ly / 2)); g.rotate(-Math.PI / 2); g.textAlign = "center"; g.fillText("y mm", 0, 0); g.restore();
  // the reference corner
  g.fillStyle = "#ffffff"; g.beginPath(); g.arc(X(0), Y(0), 6, 0, 2 * Math.PI); g.fill();
  g.textAlign = "left"; g.fillText("reference corner (0, 0)", X(0) + 10, Y(0) - 8);
  // the detection lines and their names
  const drawn = [];
  for (const l of report.lines) {
    if (!l.start_plate_mm || !l.end_plate_mm) continue;
    const [a, b] = [l.start_plate_mm, l.end_plate_mm];
    g.strokeStyle = l.pass ? "rgba(255,255,255,0.85)" : "#ff6b6b"; g.lineWidth = 2; g.setLineDash([6, 4]);
    g.beginPath(); g.moveTo(X(a[0]), Y(a[1])); g.lineTo(X(b[0]), Y(b[1])); g.stroke(); g.setLineDash([]);
    const name = lname(l), tx = X(b[0]) + 4, ty = Y(b[1]) - 4, w = g.measureText(name).width + 6;
    g.fillStyle = "rgba(6,9,11,0.8)"; g.fillRect(tx - 3, ty - 13, w, 17);
    g.fillStyle = l.pass ? "#ffffff" : "#ff9a9a"; g.fillText(name, tx, ty);
    drawn.push(name);
  }
  // the rework regions, numbered as in the list
  let shown = 0;
  for (const r of regions) {
    if (!r.p0 || !r.p1) continue;
    g.strokeStyle = "#ff2d2d"; g.lineWidth = 7; g.lineCap = "round";
    g.beginPath(); g.moveTo(X(r.p0[0]), Y(r.p0[1])); g.lineTo(X(r.p1[0]), Y(r.p1[1])); g.stroke(); g.lineCap = "butt";
    const mx = (X(r.p0[0]) + X(r.p1[0])) / 2, my = (Y(r.p0[1]) + Y(r.p1[1])) / 2;
    g.fillStyle = "#ffffff"; g.beginPath(); g.arc(mx + 14, my - 14, 10, 0, 2 * Math.PI); g.fill();
    g.fillStyle = "#a00000"; g.textAlign = "center"; g.font = "bold 13px system-ui"; g.fillText(String(r.no), mx + 14, my - 9.5);
    g.font = "13px system-ui"; g.textAlign = "left"; shown++;
  }
  // the heating lines: solid, orange on the face up, cyan on the face down, numbered in order at their start
  const heat = plan && plan.status === "plan" ? plan.lines : [];
  for (const h of heat) {
    const [a, b] = [h.start_plate_mm, h.end_plate_mm], top = h.face === "top";
    g.strokeStyle = top ? "#ffa033" : "#33d6ff"; g.lineWidth = 4;
    g.beginPath(); g.moveTo(X(a[0]), Y(a[1])); g.lineTo(X(b[0]), Y(b[1])); g.stroke();
    g.fillStyle = top ? "#ffa033" : "#33d6ff"; g.beginPath(); g.arc(X(a[0]), Y(a[1]), 11, 0, 2 * Math.PI); g.fill();
    g.fillStyle = "#06090b"; g.textAlign = "center"; g.font = "bold 12px system-ui"; g.fillText(String(h.order), X(a[0]), Y(a[1]) + 4);
    g.font = "13px system-ui"; g.textAlign = "left";
  }
  c.dataset.lines = drawn.join(","); c.dataset.regions = String(shown); c.dataset.scaleMmPerPx = (1 / k).toFixed(3);
  c.dataset.heating = heat.map((h) => h.id).join(",");
}
$("btn-reanalyse").addEventListener("click", async () => {
  const res = await api("POST", "/api/control/reanalyse", { job_id: $("btn-reanalyse").dataset.job });
  $("result-meta").textContent = res.ok ? "re-analysing" : "re-analyse refused: " + errText(res);
});

// the step of 1, 2 or 5 x 10^k giving the number of ticks over range closest to n
function niceStep(range, n) {
  const r = range || 1, p = Math.pow(10, Math.floor(Math.log10(r / n)));
  return [1, 2, 5, 10].map((m) => m * p).reduce((a, b) => (Math.abs(r / b - n) < Math.abs(r / a - n) ? b : a));
}
const tickText = (v, step) => (Math.abs(v) < step * 1e-6 ? "0" : v.toFixed(Math.max(0, -Math.floor(Math.log10(step) + 1e-9))));
// axes with ticks and a grid on both; the title sits above the plot area (nothing drawn crosses it)
// and the data are clipped to the area. opts: right (px kept for a legend), xStep (e.g. 1 for rounds)
function plotAxes(c, title, xs, ys, yBands, opts = {}) {
  const g = c.getContext("2d"), W = c.width, H = c.height, L = 52, B = 24, T = 30, R = opts.right || 12;
  if (c.dataset.clipped) g.restore();
  g.fillStyle = "#06090b"; g.fillRect(0, 0, W, H);
  const xlo = Math.min(...xs), xhi = Math.max(...xs, xlo + 1);
  let ylo = Math.min(...ys, ...yBands.map((b) => -b)), yhi = Math.max(...ys, ...yBands);
  const pad = 0.1 * (yhi - ylo || 1); ylo -= pad; yhi += pad;
  const X = (v) => L + ((v - xlo) / (xhi - xlo)) * (W - L - R), Y = (v) => T + ((yhi - v) / (yhi - ylo)) * (H - B - T);
  g.font = "13px system-ui"; g.lineWidth = 1; g.setLineDash([]);
  g.fillStyle = "#cfd8df"; g.textAlign = "left"; g.fillText(title, L, 19);
  const ticks = (lo, hi, step) => { const out = []; for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(v); return out; };
  const ys_ = niceStep(yhi - ylo, Math.max(3, Math.floor((H - B - T) / 30))), xs_ = opts.xStep || niceStep(xhi - xlo, Math.max(3, Math.floor((W - L - R) / 70)));
  const yt = ticks(ylo, yhi, ys_), xt = ticks(xlo, xhi, xs_);
  g.strokeStyle = "#1c2630"; g.fillStyle = "#9fb0bf";
  g.textAlign = "right";
  for (const v of yt) { const y = Y(v); g.beginPath(); g.moveTo(L, y); g.lineTo(W - R, y); g.stroke(); g.fillText(tickText(v, ys_), L - 5, y + 4); }
  g.textAlign = "center";
  for (const v of xt) { const x = X(v); g.beginPath(); g.moveTo(x, T); g.lineTo(x, H - B); g.stroke(); g.fillText(tickText(v, xs_), x, H - 7); }
  g.textAlign = "left";
  g.strokeStyle = "#3a4a5a"; g.strokeRect(L, T, W - L - R, H - B - T);
  c.dataset.yticks = String(yt.length); c.dataset.xticks = String(xt.length); c.dataset.plotTop = String(T);
  g.save(); g.beginPath(); g.rect(L, T, W - L - R, H - B - T); g.clip(); c.dataset.clipped = "1";
  return { g, X, Y, W, H, L, B, T, R };
}
// twelve colours apart on a dark ground; past twelve lines the colours come back dashed
const SERIES = ["#4ea1ff", "#ffb000", "#3ddc84", "#ff5c5c", "#c77dff", "#00d1d1", "#fff06b", "#ff8ad8", "#b0b0b0", "#9bd45b", "#ff9152", "#8fb3ff"];
const seriesStyle = (k) => ({ colour: SERIES[k % SERIES.length], dash: k < SERIES.length ? [] : [7, 4] });
function plotLine(c, name, s, dv, stdMm, limMm, pass) {
  const { g, X, Y } = plotAxes(c, `${name}: deviation mm along s mm`, s, dv.filter((v) => v !== null), [limMm]);
  g.fillStyle = "rgba(40,170,70,0.18)"; g.fillRect(X(s[0]), Y(stdMm), X(s[s.length - 1]) - X(s[0]), Y(-stdMm) - Y(stdMm));
  g.strokeStyle = "rgba(230,170,30,0.8)"; g.setLineDash([4, 4]);
  for (const b of [limMm, -limMm]) { g.beginPath(); g.moveTo(X(s[0]), Y(b)); g.lineTo(X(s[s.length - 1]), Y(b)); g.stroke(); }
  g.setLineDash([]); g.strokeStyle = pass ? "#6cf" : "#f66"; g.lineWidth = 2; g.beginPath();
  // null: no data there (a gap in the scan), the curve breaks
  s.forEach((sv, i) => { if (dv[i] !== null) (i && dv[i - 1] !== null ? g.lineTo(X(sv), Y(dv[i])) : g.moveTo(X(sv), Y(dv[i]))); });
  g.stroke(); c.dataset.samples = String(s.length);
}

// ------------------------------------------------------------------ History page
async function loadHistory(plate) {
  S.historyPlate = plate;
  if (plate && !$("history-plate").value) $("history-plate").value = plate;
  const q = new URLSearchParams({ plate: $("history-plate").value.trim(), date: $("history-date").value, verdict: $("history-verdict").value });
  const res = await api("GET", "/api/jobs?" + q);
  if (res.ok) {
    $("history-jobs").innerHTML = "<tr><th>plate</th><th>job</th><th>created (UTC)</th><th>state</th><th>verdict</th><th>max |Zmax| mm</th></tr>" +
      res.data.jobs.map((j) => `<tr class="clickable ${j.verdict === "fail" ? "fail" : ""}" data-job="${esc(j.job_id)}" data-plate="${esc(j.plate_id)}"><td><a href="#history/${encodeURIComponent(j.plate_id)}">${esc(j.plate_id)}</a></td><td>${esc(j.job_id)}</td><td>${esc(j.created_utc)}</td><td>${esc(j.state)}</td><td>${esc(j.verdict || "-")}</td><td>${fmt(j.max_abs_zmax_mm)}</td></tr>`).join("");
  }
  const p = $("history-plate").value.trim();
  $("history-rounds").classList.toggle("hidden", !p);
  if (!p) return;
  const rr = await api("GET", "/api/plates/" + encodeURIComponent(p) + "/rounds");
  const rounds = rr.ok ? rr.data.rounds : [];
  $("history-rounds-title").textContent = `Plate ${p}: ${rounds.length} round(s), Zmax per line (mm)`;
  $("history-rounds").dataset.rounds = String(rounds.length);
  const names = [];
  for (const r of rounds) for (const l of r.lines) if (!names.includes(l.name)) names.push(l.name);
  $("history-rounds-table").innerHTML = `<tr><th>line</th>${rounds.map((r) => `<th>round ${r.round}<br><small>${esc(r.job_id)}</small></th>`).join("")}</tr>` +
    names.map((n) => `<tr><td>${esc(n)}</td>${rounds.map((r) => { const l = r.lines.find((x) => x.name === n); return `<td style="color:${l && !l.pass ? "#f99" : ""}">${l ? fmt(l.zmax_mm) : "-"}</td>`; }).join("")}</tr>`).join("") +
    `<tr><td>verdict</td>${rounds.map((r) => `<td>${esc(r.verdict)}</td>`).join("")}</tr>`;
  // convergence: |Zmax| per line over the rounds
  const c = $("history-convergence");
  if (!rounds.length) { c.getContext("2d").clearRect(0, 0, c.width, c.height); return; }
  const xs = rounds.map((r) => r.round), all = rounds.flatMap((r) => r.lines.map((l) => Math.abs(l.zmax_mm)));
  const perCol = Math.max(1, Math.floor((c.height - 40) / 18)), cols = Math.ceil(names.length / perCol);
  const { g, X, Y, T, W } = plotAxes(c, "convergence: |Zmax| per line (mm) by round", xs.length > 1 ? xs : [1, 2], all.length ? all : [0], [0], { right: 16 + 90 * cols, xStep: 1 });
  names.forEach((n, k) => {
    const st = seriesStyle(k);
    g.strokeStyle = st.colour; g.fillStyle = st.colour; g.lineWidth = 2; g.setLineDash(st.dash); g.beginPath();
    let first = true;
    rounds.forEach((r) => { const l = r.lines.find((x) => x.name === n); if (!l) return; const x = X(r.round), y = Y(Math.abs(l.zmax_mm)); first ? g.moveTo(x, y) : g.lineTo(x, y); first = false; });
    g.stroke(); g.setLineDash([]);
    rounds.forEach((r) => { const l = r.lines.find((x) => x.name === n); if (l) g.fillRect(X(r.round) - 3, Y(Math.abs(l.zmax_mm)) - 3, 6, 6); });
  });
  // the legend beside the plot, never on its lines: a sample of each line's colour and dash, its name
  g.restore(); delete c.dataset.clipped;
  names.forEach((n, k) => {
    const st = seriesStyle(k), x = W - 90 * cols + 90 * Math.floor(k / perCol), y = T + 10 + 18 * (k % perCol);
    g.strokeStyle = st.colour; g.lineWidth = 3; g.setLineDash(st.dash); g.beginPath(); g.moveTo(x, y - 4); g.lineTo(x + 26, y - 4); g.stroke(); g.setLineDash([]);
    g.fillStyle = "#e8ecef"; g.fillText(n, x + 32, y);
  });
  c.dataset.series = JSON.stringify(names.map((n, k) => [n, seriesStyle(k).colour, seriesStyle(k).dash.join(",")]));
}
$("history-form").addEventListener("submit", (e) => { e.preventDefault(); loadHistory(null); });
$("history-jobs").addEventListener("click", (e) => {
  if (e.target.closest("a")) { $("history-plate").value = e.target.closest("tr").dataset.plate; return; }
  const tr = e.target.closest("tr[data-job]");
  if (tr) location.hash = "#result/" + encodeURIComponent(tr.dataset.job);
});

// ------------------------------------------------------------------ start
(async () => {
  const res = await api("GET", "/api/me");
  if (res.ok) afterLogin(res.data); else showLogin();
})();
