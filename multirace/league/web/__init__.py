"""`multirace league serve`: the league as a web app (Starlette on uvicorn, Jinja2 templates).

app.py the routes; queries.py what the pages and the API show; security.py size and rate limits, CSRF,
headers; media.py race videos; viewer.py rerun's web viewer; charts.py inline SVG charts; server.py serving.
"""
