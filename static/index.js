// Embed the viser viewer (same host, its own port) and show how to connect a phone.
async function init() {
  const info = await (await fetch("/api/info")).json();
  const url = `${location.protocol}//${location.hostname}:${info.viewer_port}/`;
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
