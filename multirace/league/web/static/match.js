// Loads rerun's web viewer (served by this league) into the page on request.
document.getElementById("open-viewer").addEventListener("click", function () {
  const frame = document.getElementById("viewer");
  frame.src = this.dataset.src;
  frame.hidden = false;
  this.hidden = true;
});
