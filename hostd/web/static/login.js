// The login form: POST /login sets an HttpOnly cookie, then the dashboard opens.
// A link of the form /login#token=... (what `make demo` prints) logs in by itself:
// the fragment never reaches the server's logs.
"use strict";

async function login(token) {
  const error = document.getElementById("login-error");
  error.textContent = "";
  const response = await fetch("/login", {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ token }),
  });
  if (response.ok) {
    window.location.replace("/");
    return;
  }
  const body = await response.json().catch(() => ({}));
  error.textContent = body.error || `refused (${response.status})`;
}

document.getElementById("login").addEventListener("submit", (event) => {
  event.preventDefault();
  login(document.getElementById("token").value.trim());
});

const fromLink = new URLSearchParams(window.location.hash.slice(1)).get("token");
if (fromLink) {
  history.replaceState(null, "", "/login");
  login(fromLink);
}
