// Embed the viser viewer (same host, its own port) and show how to connect a phone.
async function init() {
  const info = await (await fetch("/api/info")).json();
  let url = `${location.protocol}//${location.hostname}:${info.viewer_port}/`;
  if (info.viewer_token) {  // the presenter: the viewer's WebSocket carries the token
    const ws = `${location.protocol === "https:" ? "wss" : "ws"}://${location.hostname}:${info.viewer_port}/?token=${encodeURIComponent(info.viewer_token)}`;
    url += `?websocket=${encodeURIComponent(ws)}`;
  }
  document.body.classList.toggle("watch-only", !info.presenter);
  if (!info.presenter) document.getElementById("source").title = "watch-only: the presenter's link holds the token that allows changes";
  document.getElementById("viewer").src = url;
  document.getElementById("viewer-link").href = url;
  document.getElementById("lan-ip").textContent = info.lan_ip;
  document.getElementById("phone-port").textContent = info.phone_port;
  poll();
}
async function poll() {
  const badge = document.getElementById("source");
  try {
    const st = await (await fetch("/api/state")).json();
    badge.textContent = st.status;
    badge.className = "badge" + (st.source === "phone" ? " phone" : st.source === "phone-disconnected" ? " warn" : "");
  } catch (e) {
    badge.textContent = "server not reachable";
    badge.className = "badge warn";
  }
  setTimeout(poll, 1000);
}
init();
