-- wrk script of the HTTP benchmarks: every connection POSTs the same JSON body, read from the
-- file named by the first script argument (wrk ... -s post.lua URL -- BODY_FILE). At the end it
-- prints one line "BENCH_JSON {...}" with exact latency percentiles (microseconds), the error
-- counts, the number of non-2xx answers and the answers per status, for bench/wrk.py to parse.

local threads = {}

function setup(thread)
  table.insert(threads, thread)
end

function init(args)
  local f = assert(io.open(args[1], "rb"), "cannot open body file " .. tostring(args[1]))
  wrk.body = f:read("*a")
  f:close()
  wrk.method = "POST"
  wrk.headers["Content-Type"] = "application/json"
  non2xx = 0
  responses = 0
  statuses = {}
end

function response(status, headers, body)
  responses = responses + 1
  statuses[status] = (statuses[status] or 0) + 1
  if status < 200 or status > 299 then
    non2xx = non2xx + 1
  end
end

function done(summary, latency, requests)
  local non, seen, by_status = 0, 0, {}
  for _, t in ipairs(threads) do
    non = non + (t:get("non2xx") or 0)
    seen = seen + (t:get("responses") or 0)
    for code, n in pairs(t:get("statuses") or {}) do
      by_status[code] = (by_status[code] or 0) + n
    end
  end
  local parts = {}
  for code, n in pairs(by_status) do
    table.insert(parts, string.format('"%d": %d', code, n))
  end
  local e = summary.errors
  io.write(string.format(
    'BENCH_JSON {"duration_us": %d, "requests": %d, "responses": %d, "bytes": %d, ' ..
    '"connect_errors": %d, "read_errors": %d, "write_errors": %d, "status_errors": %d, ' ..
    '"timeouts": %d, "non2xx": %d, "statuses": {%s}, "latency_us": {"min": %d, "mean": %.1f, "stdev": %.1f, ' ..
    '"max": %d, "p50": %d, "p90": %d, "p99": %d, "p999": %d}}\n',
    summary.duration, summary.requests, seen, summary.bytes, e.connect, e.read, e.write, e.status,
    e.timeout, non, table.concat(parts, ", "), latency.min, latency.mean, latency.stdev, latency.max,
    latency:percentile(50), latency:percentile(90), latency:percentile(99), latency:percentile(99.9)))
end
