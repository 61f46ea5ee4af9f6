// The REST API as the browser sees it: the key (kept in sessionStorage, so it dies with the tab),
// JSON requests with errors turned into sentences, and the upload with progress events.

const KEY_NAME = "fluidnexus.apiKey";

export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

/** Called when a request answers 401 after sign-in: the key was revoked meanwhile. */
let onUnauthorized = () => {};
export function setUnauthorizedHandler(handler) { onUnauthorized = handler; }

export const getKey = () => sessionStorage.getItem(KEY_NAME);
export const setKey = (key) => sessionStorage.setItem(KEY_NAME, key);
export const clearKey = () => sessionStorage.removeItem(KEY_NAME);

/** The API's error body in words: FastAPI sends `detail` as a string, or as a list of field errors. */
function describeError(status, body) {
  const detail = body && body.detail;
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((e) => `${(e.loc || []).filter((p) => p !== "body").join(".")}: ${e.msg}`).join("; ");
  }
  if (status === 413) return "the upload is larger than the server accepts";
  return `the server answered ${status}`;
}

async function parseBody(response) {
  const text = await response.text();
  try { return text ? JSON.parse(text) : null; } catch { return { detail: text }; }
}

/** fetch() a /v1 route with the key; JSON in and out; throws ApiError with the server's message. */
export async function api(path, { method = "GET", body, key = getKey(), headers = {} } = {}) {
  const init = { method, headers: { ...headers, Authorization: `Bearer ${key}` } };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(path, init);
  } catch (error) {
    throw new ApiError(0, `the server cannot be reached (${error.message})`);
  }
  const data = response.status === 204 ? null : await parseBody(response);
  if (!response.ok) {
    if (response.status === 401) onUnauthorized();
    throw new ApiError(response.status, describeError(response.status, data));
  }
  return data;
}

/** Check a key before keeping it; the message says what a user can do about a refused one. */
export async function checkKey(key) {
  try {
    await api("/v1/jobs?limit=1", { key });
  } catch (error) {
    if (error.status === 401) {
      throw new ApiError(401, "This API key was not accepted: it is wrong or has been revoked. "
        + "Check that it was copied whole, or create a new one with: fluidnexus keys create --owner NAME");
    }
    throw error;
  }
}

/** POST a multipart form with XMLHttpRequest, whose upload events give a progress bar. */
export function uploadForm(path, form, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", path);
    xhr.setRequestHeader("Authorization", `Bearer ${getKey()}`);
    xhr.upload.addEventListener("progress", (event) => {
      if (event.lengthComputable) onProgress(event.loaded / event.total);
    });
    xhr.addEventListener("load", () => {
      let data = null;
      try { data = JSON.parse(xhr.responseText); } catch { data = { detail: xhr.responseText }; }
      if (xhr.status >= 200 && xhr.status < 300) resolve(data);
      else {
        if (xhr.status === 401) onUnauthorized();
        reject(new ApiError(xhr.status, describeError(xhr.status, data)));
      }
    });
    xhr.addEventListener("error", () => reject(new ApiError(0, "the upload failed: the server cannot be reached")));
    xhr.send(form);
  });
}
