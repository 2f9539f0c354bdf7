// The daemon's REST API (/api/v1) as used by the operator page: bearer token, JSON errors in words, and the
// Server-Sent Events stream read with fetch() (EventSource cannot send an Authorization header).

export const PREFIX = "/api/v1";
const TOKEN_KEY = "autotuner.token";

export function getToken() { return sessionStorage.getItem(TOKEN_KEY); }
export function setToken(token) { sessionStorage.setItem(TOKEN_KEY, token); }
export function clearToken() { sessionStorage.removeItem(TOKEN_KEY); }

// An error answer of the API: status, code (busy, forbidden, invalid, ...), message, and the fields a 422 names.
export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
    this.fields = status === 422 ? fieldsOf(message) : [];
  }

  // The error in words, for the operator.
  get text() {
    const m = this.message;
    switch (this.status) {
      case 0: return `The daemon cannot be reached (${m}).`;
      case 401: return `Your token was not accepted (401): log in again with a valid token.`;
      case 403: return `Not allowed (403): ${m}.`;
      case 404: return `Not found (404): ${m}.`;
      case 409:
        if (this.code === "busy") return `Refused (409): the loop is busy — ${m}.`;
        if (this.code === "group_busy") return `Refused (409): another loop of the exclusion group is tuning — ${m}.`;
        if (this.code === "idle") return `Refused (409): nothing to abort — ${m}.`;
        if (this.code === "nothing_to_apply") return `Refused (409): there are no new gains to apply — ${m}.`;
        return `Refused (409): ${m}.`;
      case 422: return `Invalid input (422): ${m}.`;
      case 502: return `The controller could not be reached (502): ${m}.`;
      default: return `Error ${this.status} (${this.code}): ${m}.`;
    }
  }
}

// "amp: Input should be greater than 0; ms: ..." → ["amp", "ms"] (the API names the field before a colon).
export function fieldsOf(message) {
  return String(message).split("; ").map((part) => part.split(":")[0].trim()).filter((f) => /^[\w.[\]]+$/.test(f));
}

function headers(extra) {
  const h = { Accept: "application/json", ...extra };
  const token = getToken();
  if (token) h.Authorization = `Bearer ${token}`;
  return h;
}

// Listeners for 401 answers (the page goes back to the login).
const unauthorized = new Set();
export function onUnauthorized(fn) { unauthorized.add(fn); }

// A request to the API; the parsed JSON, or throws ApiError.
export async function api(method, path, body, token) {
  const init = { method, headers: headers(body === undefined ? {} : { "Content-Type": "application/json" }) };
  if (token !== undefined) init.headers.Authorization = `Bearer ${token}`;
  if (body !== undefined) init.body = JSON.stringify(body);
  let response;
  try {
    response = await fetch(PREFIX + path, init);
  } catch (exc) {
    throw new ApiError(0, "network", exc.message || String(exc));
  }
  const text = await response.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = null; }
  if (!response.ok) {
    const err = new ApiError(response.status, data?.code ?? "error", data?.message ?? (text || response.statusText));
    if (response.status === 401 && token === undefined) unauthorized.forEach((fn) => fn(err));
    throw err;
  }
  return data;
}

export const get = (path) => api("GET", path);
export const post = (path, body) => api("POST", path, body);

// Who the token is: {name, role} (401 for a token the daemon does not know).
export const whoami = (token) => api("GET", "/whoami", undefined, token);

// The SSE stream of a loop, read with fetch() and parsed here; reconnects by itself.
// handlers: {state(data), sample(data), status(connected: bool, detail)}. Returns {close()}.
export function eventStream(path, handlers) {
  let closed = false;
  let controller = null;
  let delay = 500;
  let timer = null;
  // No byte for this long (keep-alives come every 15 s): the stream is dead.
  const SILENCE_MS = 40000;

  function dispatch(block) {
    let event = "message";
    const data = [];
    for (const line of block.split("\n")) {
      if (!line || line.startsWith(":")) continue;
      const colon = line.indexOf(":");
      const field = colon < 0 ? line : line.slice(0, colon);
      let value = colon < 0 ? "" : line.slice(colon + 1);
      if (value.startsWith(" ")) value = value.slice(1);
      if (field === "event") event = value;
      else if (field === "data") data.push(value);
    }
    if (!data.length) return;
    let parsed;
    try { parsed = JSON.parse(data.join("\n")); } catch { return; }
    const fn = handlers[event];
    if (fn) fn(parsed);
  }

  async function run() {
    controller = new AbortController();
    let watchdog = null;
    const arm = () => {
      clearTimeout(watchdog);
      watchdog = setTimeout(() => controller.abort(), SILENCE_MS);
    };
    let reason = "the stream ended";
    try {
      arm();
      const response = await fetch(PREFIX + path, { headers: headers({ Accept: "text/event-stream" }),
                                                    signal: controller.signal, cache: "no-store" });
      if (!response.ok) {
        let body = null;
        try { body = await response.json(); } catch { body = null; }
        const err = new ApiError(response.status, body?.code ?? "error", body?.message ?? response.statusText);
        if (response.status === 401) { unauthorized.forEach((fn) => fn(err)); return; }
        throw err;
      }
      handlers.status?.(true);
      delay = 500;
      const reader = response.body.getReader();
      const decoder = new TextDecoder();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        arm();
        buffer += decoder.decode(value, { stream: true }).replace(/\r\n?/g, "\n");
        let cut;
        while ((cut = buffer.indexOf("\n\n")) >= 0) {
          dispatch(buffer.slice(0, cut));
          buffer = buffer.slice(cut + 2);
        }
      }
    } catch (exc) {
      reason = exc instanceof ApiError ? exc.text : (exc.name === "AbortError" ? "no data" : exc.message);
    } finally {
      clearTimeout(watchdog);
    }
    if (closed) return;
    handlers.status?.(false, reason);
    timer = setTimeout(run, delay);
    delay = Math.min(delay * 2, 5000);
  }

  run();
  return {
    close() {
      closed = true;
      clearTimeout(timer);
      controller?.abort();
    },
  };
}
