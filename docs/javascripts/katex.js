// Render the math that pymdownx.arithmatex (generic mode) marks: \( ... \) inline, \[ ... \] display,
// each inside an element of class "arithmatex". KaTeX is vendored under javascripts/vendor/katex/
// (no CDN). Material's instant navigation swaps pages without a reload, so render on every page
// load it announces (document$), not only on the first.
(function () {
  function render(root) {
    if (typeof renderMathInElement !== "function") {
      return;
    }
    root.querySelectorAll(".arithmatex").forEach(function (element) {
      renderMathInElement(element, {
        delimiters: [
          { left: "\\(", right: "\\)", display: false },
          { left: "\\[", right: "\\]", display: true },
        ],
        throwOnError: false,
      });
    });
  }
  if (typeof document$ !== "undefined") {
    document$.subscribe(function ({ body }) {
      render(body);
    });
  } else {
    document.addEventListener("DOMContentLoaded", function () {
      render(document.body);
    });
  }
})();
