// Typesets arithmatex's generic output (pymdownx.arithmatex, generic: true) with the vendored
// KaTeX: "\( ... \)" in span.arithmatex (inline) and "\[ ... \]" in div.arithmatex (display).
// A formula KaTeX cannot parse shows as a red .katex-error element (the docs test looks for them).
(function () {
  "use strict";
  var delimiters = [
    { left: "\\(", right: "\\)", display: false },
    { left: "\\[", right: "\\]", display: true },
  ];
  function typeset(root) {
    var nodes = (root || document).querySelectorAll(".arithmatex");
    for (var i = 0; i < nodes.length; i++) {
      renderMathInElement(nodes[i], { delimiters: delimiters, throwOnError: false });
    }
  }
  if (typeof document$ !== "undefined") {
    // Material for MkDocs: typeset each page it shows (instant navigation included).
    document$.subscribe(function () { typeset(document); });
  } else if (document.readyState === "loading") {
    document.addEventListener("DOMContentLoaded", function () { typeset(document); });
  } else {
    typeset(document);
  }
})();
