// The read token, when the server needs one (auth.read_tokens or a token file's
// `read` scope): open the dashboard as /#token=<token>. A URL fragment never
// leaves the browser; the token is kept for this tab only (sessionStorage).
const KEY = "stillmap-token";
const fromHash = new URLSearchParams(location.hash.slice(1)).get("token");
if (fromHash) {
  sessionStorage.setItem(KEY, fromHash);
  history.replaceState(null, "", location.pathname + location.search);
}
const token = sessionStorage.getItem(KEY);

// `url` carrying the token as ?access_token= (an EventSource and an <img> cannot
// send an Authorization header); unchanged without a token.
export function authed(url) {
  if (!token) return url;
  return `${url}${url.includes("?") ? "&" : "?"}access_token=${encodeURIComponent(token)}`;
}
