// The page: sign-in, then four views chosen by the URL hash (#upload, #jobs, #results/ID,
// #whatif/ID), so the browser's back button and bookmarks work.

import { $ } from "./dom.js";
import { ApiError, api, checkKey, clearKey, getKey, setKey, setUnauthorizedHandler } from "./api.js";
import { describeJob, initJobs, jobs, pollNow, requestOf, shortId, startPolling, stopPolling } from "./jobs.js";
import { bound, loadLimits } from "./limits.js";
import { initResults, showResults, stopSync } from "./results.js";
import { initUpload } from "./upload.js";
import { initWhatif, leaveWhatif, showWhatif } from "./whatif.js";

const VIEWS = ["signin", "upload", "jobs", "results", "whatif"];

const NOTICE_MS = 12000;
let noticeTimer = null;

/** A short message at the top (what an action did); it goes away by itself. */
function notice(text) {
  $("notice").textContent = text;
  $("notice").hidden = !text;
  clearTimeout(noticeTimer);
  if (text) noticeTimer = setTimeout(() => notice(""), NOTICE_MS);
}

function show(name) {
  for (const view of VIEWS) $(`view-${view}`).hidden = view !== name;
  for (const button of document.querySelectorAll("nav [data-view]")) {
    if (button.dataset.view === name) button.setAttribute("aria-current", "page");
    else button.removeAttribute("aria-current");
  }
  $("nav").hidden = name === "signin";
}

async function route() {
  if (!getKey()) {
    show("signin");
    $("api-key").focus();
    return;
  }
  stopSync();
  leaveWhatif();
  const [name, id] = location.hash.slice(1).split("/");
  if (name === "results" && id) { show("results"); await showResults(id); }
  else if (name === "whatif" && id) { show("whatif"); await showWhatif(id); }
  else if (name === "upload") show("upload");
  else { show("jobs"); pollNow(); }
  const heading = document.querySelector("section:not([hidden]) h2");
  if (heading) { heading.tabIndex = -1; heading.focus(); } // screen readers hear the new view
}

const go = (hash) => { if (location.hash === hash) route(); else location.hash = hash; };

function signOut(message) {
  clearKey();
  stopPolling();
  notice("");
  $("signin-error").textContent = message || "";
  go("#signin");
}

async function signIn(event) {
  event.preventDefault();
  const key = $("api-key").value.trim();
  $("signin-error").textContent = "";
  try {
    await checkKey(key);
  } catch (error) {
    $("signin-error").textContent = error instanceof ApiError ? error.message : String(error);
    return;
  }
  setKey(key);
  $("api-key").value = "";
  startPolling();
  go("#jobs");
}

/** What a what-if plays next to, as the notice says it: a factual prediction queued with it, one
 * already there, or (branched inside the run) the run itself in its side-by-side video. */
function whatifCompanion({ queued, existing, branched }) {
  if (branched !== null) return `, branched at frame ${branched}: its side-by-side video shows the run without the intervention (no factual prediction needed)`;
  if (queued) return `, with the factual prediction ${shortId(queued.id)} it plays next to`;
  return `; it plays next to the factual prediction ${shortId(existing.id)}, already there`;
}

async function act(what, promise) {
  try {
    const job = await promise;
    notice(job ? `${what}: ${describeJob(job)}.` : what);
  } catch (error) {
    notice(`${what} refused: ${error.message}`);
  }
  pollNow();
}

function init() {
  setUnauthorizedHandler(() => signOut("Your API key is no longer accepted (it was revoked, or the server's keys changed). Sign in with a valid key."));
  $("signin-form").addEventListener("submit", signIn);
  $("sign-out").addEventListener("click", () => signOut(""));
  for (const button of document.querySelectorAll("nav [data-view]")) {
    button.addEventListener("click", () => go(`#${button.dataset.view}`));
  }
  initUpload((scene, job) => {
    notice(job ? `Scene ${scene.name || scene.id} uploaded; reconstruction ${shortId(job.id)} queued.`
      : `Scene ${scene.name || scene.id} uploaded.`);
    go("#jobs");
  });
  initJobs({
    results: (id) => go(`#results/${id}`),
    whatif: (id) => go(`#whatif/${id}`),
    predict: (id) => act("Prediction started", api("/v1/jobs", { method: "POST",
      body: { type: "predict", parent_job_id: id, params: { frames: Number($("predict-frames").value) } } })),
    cancel: (id) => act("Cancel requested", api(`/v1/jobs/${id}/cancel`, { method: "POST" })),
    retry: (id) => act("Sent again", api("/v1/jobs", { method: "POST", body: requestOf(jobs.get(id)) })),
  });
  initResults();
  loadLimits().then((limits) => bound($("predict-frames"), limits.predict.frames), () => {}); // the upload view says why not
  initWhatif((job, factual) => {
    notice(`What-if ${shortId(job.id)} queued${whatifCompanion(factual)}. Open its Results when it has succeeded.`);
    go("#jobs");
  }, (job) => {
    notice(`Reconstruction ${shortId(job.id)} queued with your source hint.`);
    go("#jobs");
  });
  window.addEventListener("hashchange", route);
  if (getKey()) startPolling();
  route();
}

init();
