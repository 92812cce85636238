// The REST API from the browser: the operator's bearer token and readable errors.

const TOKEN_KEY = 'agv-fe-token';

export function getToken() {
  try {
    return localStorage.getItem(TOKEN_KEY) || '';
  } catch {
    return '';
  }
}

export function setToken(token) {
  try {
    if (token) localStorage.setItem(TOKEN_KEY, token);
    else localStorage.removeItem(TOKEN_KEY);
  } catch {
    // storage disabled: the token lasts as long as the page
  }
  memoryToken = token;
}

let memoryToken = getToken();

export function authHeaders() {
  const token = memoryToken || getToken();
  return token ? { Authorization: `Bearer ${token}` } : {};
}

export class ApiError extends Error {
  constructor(status, message, problems = []) {
    super(message);
    this.status = status;
    this.problems = problems;
  }
}

/** FastAPI's error body in words: a 'detail' string, or a list of validation problems. */
function explain(status, body) {
  const detail = body && body.detail;
  if (Array.isArray(detail)) {
    const problems = detail.map((p) => `${(p.loc || []).filter((x) => x !== 'body').join('.')}: ${p.msg}`);
    return new ApiError(status, 'the values were refused', problems);
  }
  if (status === 401) return new ApiError(status, 'the API token is missing or refused: enter it at the top right');
  return new ApiError(status, typeof detail === 'string' ? detail : `HTTP ${status}`);
}

export async function api(method, path, body) {
  const headers = { Accept: 'application/json', ...authHeaders() };
  if (body !== undefined) headers['Content-Type'] = 'application/json';
  let response;
  try {
    response = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  } catch (err) {
    throw new ApiError(0, `the service did not answer (${err.message})`);
  }
  const text = await response.text();
  let data = null;
  try {
    data = text ? JSON.parse(text) : null;
  } catch {
    data = null;
  }
  if (!response.ok) throw explain(response.status, data);
  return data;
}
