"""A small HTTP server for tests/http.rs: serves one directory with byte ranges, or misbehaves
on purpose. Usage: http_server.py DIR MODE, MODE one of
  ranges  honours Range (206, Content-Range), ETag from size and mtime
  short   honours Range but ends every body of more than 1000 bytes at half its announced length
  etag    honours Range but gives a new ETag to every response (a file that keeps changing)
Prints the port it listens on, then serves until killed."""
import http.server, os, socketserver, sys

root, mode = sys.argv[1], sys.argv[2]
count = [0]

class H(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):
        pass

    def do_GET(self):
        path = os.path.join(root, self.path.lstrip("/"))
        if not os.path.isfile(path):
            self.send_error(404)
            return
        data = open(path, "rb").read()
        st = os.stat(path)
        etag = f'"{st.st_size}-{int(st.st_mtime)}"'
        if mode == "etag":
            count[0] += 1
            etag = f'"v{count[0]}"'
        start, end = 0, len(data) - 1
        status = 200
        r = self.headers.get("Range")
        if r and r.startswith("bytes="):
            a, b = r[6:].split("-")
            start, end = int(a), min(int(b) if b else len(data) - 1, len(data) - 1)
            status = 206
        body = data[start:end + 1]
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("ETag", etag)
        if status == 206:
            self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
        self.end_headers()
        if mode == "short" and len(body) > 1000:
            body = body[: len(body) // 2]
        self.wfile.write(body)
        self.wfile.flush()

class S(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True

s = S(("127.0.0.1", 0), H)
print(s.server_address[1], flush=True)
s.serve_forever()
