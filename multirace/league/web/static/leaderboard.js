// Keeps the leaderboard current: polls /api/leaderboard and reloads the page when the results changed.
(function () {
  async function poll() {
    const summary = document.getElementById("summary");
    try {
      const response = await fetch("/api/leaderboard", { cache: "no-store" });
      const data = await response.json();
      if (data.leaderboard.signature !== summary.dataset.signature) {
        const fresh = new DOMParser().parseFromString(await (await fetch("/", { cache: "no-store" })).text(), "text/html");
        for (const id of ["summary", "standings", "latest"]) {
          document.getElementById(id).replaceWith(fresh.getElementById(id));
        }
      }
    } catch (e) { /* the server is restarting: try again next time */ }
    setTimeout(poll, 3000);
  }
  setTimeout(poll, 3000);
})();
