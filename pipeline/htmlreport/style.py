"""The report's style sheet, inline in every page (no file, font or image outside the page)."""

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,'Helvetica Neue',Arial,sans-serif;color:#1d1d1f;
background:#fff;margin:0;line-height:1.45}
main{max-width:1200px;margin:0 auto;padding:1.2em 1.5em 3em}
h1{font-size:1.6em;margin:.2em 0}
h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
.meta{color:#666;font-size:.9em;margin-top:0}
.verdict{border-left:.5em solid #888;background:#f4f4f4;padding:.6em 1em;margin:1em 0;border-radius:.3em}
.verdict .level{font-weight:700;letter-spacing:.08em;margin:.1em 0}
.verdict .headline{font-size:1.15em;margin:.2em 0 .5em}
.verdict.good{border-color:#2e7d32;background:#edf7ee}
.verdict.good .level{color:#2e7d32}
.verdict.poor{border-color:#b26a00;background:#fff5e5}
.verdict.poor .level{color:#b26a00}
.verdict.unusable{border-color:#c62828;background:#fdecec}
.verdict.unusable .level{color:#c62828}
.verdict.info{border-color:#455a64;background:#eef2f4}
table{border-collapse:collapse;margin:.6em 0 1em;font-size:.92em}
caption{text-align:left;color:#444;padding:.2em 0;font-style:italic}
th,td{border:1px solid #d0d0d0;padding:.25em .55em;vertical-align:top}
th{background:#f0f0f0;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:1em 0}
figure img{max-width:100%;height:auto;border:1px solid #e0e0e0}
figcaption{color:#444;font-size:.9em}
pre{background:#f6f6f6;padding:.6em;overflow-x:auto}
details{margin:1em 0}
summary{cursor:pointer;font-weight:600}
"""
