"""The installed `deocc` wheel: the example scene's cloud equals the CLI's bit for bit, two
threads overlap in `run` (the GIL is released), bad input raises ValueError naming the argument,
non-contiguous arrays are copied, grasp / place answer, and the service client works.

Run by scripts/test_python.sh: python tests/test_deocc.py PATH_TO_DEOCC_BINARY
"""

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import unittest

import numpy as np

import deocc

DEOCC = os.path.abspath(sys.argv.pop(1)) if len(sys.argv) > 1 else "deocc"
TMP = tempfile.mkdtemp(prefix="deocc-py-")


def cli_example():
    """`deocc run --example` once: its input scene folder and its completed cloud."""
    out = os.path.join(TMP, "cli")
    if not os.path.exists(os.path.join(out, "completed.ply")):
        subprocess.run([DEOCC, "run", "--example", "--out", out], check=True,
                       stdout=subprocess.DEVNULL)
    return os.path.join(out, "input"), os.path.join(out, "completed.ply")


def small(frames, n=2):
    return [dict(f) for f in frames[:n]]


class Deocc(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.scene, cls.ply = cli_example()
        cls.frames, cls.structure = deocc.read_scene(cls.scene)

    def test_example_matches_the_cli_bit_for_bit(self):
        res = deocc.run(self.frames, structure_ids=self.structure)
        cli = deocc.read_ply(self.ply)
        self.assertEqual(res["points"].dtype, np.float32)
        self.assertEqual(res["points"].shape[1], 3)
        self.assertGreater(len(res["points"]), 100_000)
        self.assertTrue(np.array_equal(res["points"], cli["points"]))
        self.assertTrue(np.array_equal(res["colors"], cli["colors"]))
        self.assertTrue(np.array_equal(res["instance"], cli["instance"]))
        self.assertTrue(np.array_equal(res["provenance"], cli["provenance"]))
        self.assertTrue(np.array_equal(res["confidence"], cli["confidence"]))
        # Observed points are certain; generated ones carry the completer's probability.
        observed = res["provenance"] == 0
        self.assertTrue(np.all(res["confidence"][observed] == 1.0))
        self.assertTrue(np.all((res["confidence"] >= 0.0) & (res["confidence"] <= 1.0)))
        self.assertLess(res["confidence"][~observed].mean(), 1.0)
        # Observed points are exact; generated ones carry how far off they may be, in metres.
        self.assertTrue(np.array_equal(res["expected_error"], cli["expected_error"]))
        self.assertTrue(np.all(res["expected_error"][observed] == 0.0))
        self.assertGreater(res["expected_error"][~observed].mean(), 0.0)
        self.assertLess(res["expected_error"].max(), 1.0)
        self.assertEqual(res["report"]["frames"], len(self.frames))

    def test_two_threads_overlap_and_python_runs_meanwhile(self):
        frames = small(self.frames, 3)
        deocc.run(frames, completer="rules")  # warm
        spans, ticks, done = [], [0], threading.Event()

        def count():
            while not done.is_set():
                ticks[0] += 1

        def work():
            t0 = time.perf_counter()
            deocc.run(frames, completer="rules")
            spans.append((t0, time.perf_counter()))

        counter = threading.Thread(target=count)
        counter.start()
        workers = [threading.Thread(target=work) for _ in range(2)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        done.set()
        counter.join()
        (a0, a1), (b0, b1) = spans
        self.assertLess(max(a0, b0), min(a1, b1), "the two runs did not overlap")
        # With the GIL held for a whole run, the counter would stall for its duration.
        self.assertGreater(ticks[0], 10_000)

    def test_bad_input_names_the_argument(self):
        f = small(self.frames, 1)
        bad = dict(f[0], depth=f[0]["depth"][:, :-1])
        with self.assertRaisesRegex(ValueError, r"frames\[0\]\.depth"):
            deocc.run([bad], completer="rules")
        bad = dict(f[0], depth=f[0]["depth"].astype(np.float64))
        with self.assertRaisesRegex(ValueError, r"frames\[0\]\['depth'\]"):
            deocc.run([bad], completer="rules")
        bad = dict(f[0], rgb=f[0]["rgb"][:, :, :2])
        with self.assertRaisesRegex(ValueError, r"frames\[0\]\['rgb'\]: expected shape"):
            deocc.run([bad], completer="rules")
        bad = dict(f[0], K=[[1, 0], [0, 1]])
        with self.assertRaisesRegex(ValueError, r"frames\[0\]\['K'\]"):
            deocc.run([bad], completer="rules")
        bad = dict(f[0])
        del bad["depth"]
        with self.assertRaisesRegex(ValueError, r'frames\[0\]: missing "depth"'):
            deocc.run([bad], completer="rules")
        bad = dict(f[0], distortion_model="kb8", D=[0.1, 0.0, 0.0, 0.0])
        with self.assertRaisesRegex(ValueError, r"frames\[0\]\.camera_info\.d.*unknown distortion"):
            deocc.run([bad], completer="rules")
        # A stated lens is taken and removed on arrival.
        lens = dict(f[0], distortion_model="plumb_bob", D=[-0.05, 0.01, 0.0, 0.0, 0.0])
        self.assertGreater(len(deocc.run([lens], completer="rules")["points"]), 1000)
        with self.assertRaisesRegex(ValueError, "options_json"):
            deocc.run(f, completer="rules", options={"stpes": 4})
        with self.assertRaisesRegex(ValueError, "completer"):
            deocc.run(f, completer="magic")

    def test_non_contiguous_arrays_are_copied(self):
        f = small(self.frames, 2)
        def strided(a):
            big = np.zeros((a.shape[0], 2 * a.shape[1]) + a.shape[2:], a.dtype)
            big[:, ::2] = a
            return big[:, ::2]

        view = [dict(x, rgb=strided(x["rgb"]), depth=strided(x["depth"])) for x in f]
        self.assertFalse(view[0]["rgb"].flags["C_CONTIGUOUS"])
        a = deocc.run(f, completer="rules")
        b = deocc.run(view, completer="rules")
        self.assertTrue(np.array_equal(a["points"], b["points"]))
        # Millimetres as uint16 give the same cloud as metres as float32.
        mm = [dict(x, depth=np.round(x["depth"] * 1000).astype(np.uint16)) for x in f]
        c = deocc.run(mm, completer="rules")
        self.assertTrue(np.array_equal(a["points"], c["points"]))

    def test_placing_options_make_thinner_completions(self):
        opts = deocc.placing_options()
        every = opts["completers"]["*"]
        self.assertLess(every["max_thickness_m"], 0.1)
        self.assertGreater(every["max_thickness_per_width"], 0.0)
        f = small(self.frames, 3)
        thick = deocc.run(f, completer="rules")
        thin = deocc.run(f, completer="rules", options=opts)
        self.assertLess(len(thin["points"]), len(thick["points"]))

    def test_depth_holes_are_filled_on_request(self):
        f = small(self.frames, 2)
        for frame in f:
            d = np.array(frame["depth"], copy=True)
            d[:, ::12] = 0  # a lost column every 12 pixels
            frame["depth"] = d
        plain = deocc.run(f, completer="rules")
        self.assertEqual(plain["report"]["depth_fill"], [])
        filled = deocc.run(f, completer="rules", options={"fill_depth_max_gap_px": 8})
        fills = filled["report"]["depth_fill"]
        self.assertEqual(len(fills), 2)
        self.assertTrue(all(x["filled"] > 0 for x in fills))
        self.assertGreater(len(filled["observed"]["points"]), len(plain["observed"]["points"]))
        with self.assertRaisesRegex(ValueError, "fill_depth_max_gap_px"):
            deocc.run(f, completer="rules", options={"fill_depth_max_gap_px": 500})

    def test_grasp_and_place_answer(self):
        res = deocc.run(small(self.frames, 3), completer="rules")
        placed = deocc.place(res["points"], footprint=(0.08, 0.08), height=0.12)
        self.assertIn("maps", placed)
        if placed["found"]:
            self.assertEqual(len(placed["position"]), 3)
        with self.assertRaisesRegex(ValueError, "target"):
            deocc.grasp(res["points"], res["instance"], 60000)
        with self.assertRaisesRegex(ValueError, r"points: expected shape \(N, 3\)"):
            deocc.place(res["points"][:, :2].copy())
        # A NaN robot position returned found=True with score NaN; settings out of range and
        # options that are not an object are refused naming them.
        with self.assertRaisesRegex(ValueError, "robot"):
            deocc.place(res["points"], robot=(float("nan"),) * 3)
        target = int(next(i for i in res["instance"] if i != 0))
        for options, field in [({"approaches": 10**12}, "approaches"),
                               ({"normal_neighbours": 0}, "normal_neighbours"),
                               ([], "JSON object"), ([4], "JSON object")]:
            with self.assertRaisesRegex(ValueError, field):
                deocc.grasp(res["points"], res["instance"], target, options=options)
        with self.assertRaisesRegex(ValueError, "JSON object"):
            deocc.run(small(self.frames, 1), completer="rules", options=[])

    def test_target_at_a_pixel(self):
        # The pixel deepest inside an object's mask in the first view names that object.
        f = self.frames[0]
        res = deocc.run(small(self.frames, 1), completer="rules",
                        structure_ids=self.structure)
        ids = f["instances"].astype(np.int64)
        best, best_r = None, 0
        for v in range(8, ids.shape[0] - 8, 2):
            for u in range(8, ids.shape[1] - 8, 2):
                i = ids[v, u]
                if i == 0 or i in self.structure:
                    continue
                r = 0
                while r < 7 and (ids[v - r - 1:v + r + 2, u - r - 1:u + r + 2] == i).all():
                    r += 1
                if r > best_r:
                    best, best_r = (u, v, int(i)), r
        u, v, want = best
        camera = {"K": f["K"], "width": ids.shape[1], "height": ids.shape[0], "pose": f["pose"]}
        got = deocc.target_at(res["points"], res["instance"], (u + 0.5, v + 0.5), camera)
        self.assertEqual(got, want)
        with self.assertRaisesRegex(ValueError, "outside"):
            deocc.target_at(res["points"], res["instance"], (1e5, 3), camera)
        with self.assertRaisesRegex(ValueError, "width"):
            deocc.target_at(res["points"], res["instance"], (3, 3), {"K": f["K"]})

    def test_ctrl_c_stops_a_run(self):
        # A run goes on without the GIL; Ctrl-C used to be ignored until it ended.
        scene, _ = cli_example()
        # A shell's background job starts with SIGINT ignored, and Python then installs no
        # KeyboardInterrupt handler: put the default one back, so the test does not depend on
        # how it was launched.
        code = (
            "import deocc, signal, sys, time\n"
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
            f"frames, _ = deocc.read_scene({scene!r})\n"
            "print('ready', flush=True)\n"
            "t = time.time()\n"
            "try:\n"
            "    for _ in range(20):\n"
            "        deocc.run(frames, completer='gldot,rules')\n"
            "except KeyboardInterrupt:\n"
            "    print(f'interrupted after {time.time() - t:.2f}', flush=True)\n"
            "    sys.exit(3)\n"
        )
        p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        self.assertEqual(p.stdout.readline().strip(), "ready")
        time.sleep(1.5)
        t = time.time()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
        self.assertEqual(p.returncode, 3, out + err)
        self.assertIn("interrupted", out)
        self.assertLess(time.time() - t, 20.0)

    def test_the_service_client(self):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        server = subprocess.Popen(
            [DEOCC, "serve", "--listen", f"127.0.0.1:{port}", "--completer", "rules"],
            stderr=subprocess.PIPE, text=True)
        try:
            client = None
            for _ in range(600):
                try:
                    client = deocc.Client(f"http://127.0.0.1:{port}")
                    break
                except RuntimeError:
                    time.sleep(0.1)
            self.assertIsNotNone(client, "the server did not come up")
            self.assertTrue(client.health()["serving"])
            f = small(self.frames, 2)
            remote = client.complete(f)
            local = deocc.run(f, completer="rules")
            self.assertTrue(np.array_equal(remote["points"], local["points"]))
            self.assertIn("complete", remote["stages"])
            with self.assertRaisesRegex(ValueError, r"frames\[0\]\.camera_info\.k"):
                client.complete([dict(f[0], K=[[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]])])
            # A transposed K, and timeouts that panicked (Duration::from_secs_f64, tonic).
            K = np.asarray(f[0]["K"], dtype=np.float64)
            with self.assertRaisesRegex(ValueError, "transposed"):
                client.complete([dict(f[0], K=K.T.copy())])
            for t in (1e300, 1e15, float("inf"), -1.0):
                with self.assertRaisesRegex(ValueError, "timeout_s"):
                    client.complete(f, timeout_s=t)
            del client
        finally:
            server.terminate()
            code = server.wait(timeout=60)
            err = server.stderr.read()
            server.stderr.close()
            self.assertEqual(code, 0, err)


if __name__ == "__main__":
    unittest.main(verbosity=2)
