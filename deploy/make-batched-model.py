#!/usr/bin/env python3
"""Give a batch-1 YOLOv8-seg ONNX export a symbolic batch dimension, and prove it.

The shipped models (shared/models/yolov8n-seg_fp32_{320,640}.onnx, see MODELS.md there)
take `images` f32 [1,3,S,S] and give `output0` [1,116,N] and `output1` [1,32,S/4,S/4].
Besides the declared shapes, the detection head hard-codes batch 1 in the shape
constants of its Reshape nodes ([1,64,-1], [1,80,-1], [1,32,-1], the DFL's [1,4,16,N]
and [1,4,N]). This script:

  1. names dim 0 of every graph input and output `batch`;
  2. finds, by shape inference with that symbolic batch, every Reshape whose data
     carries the batch in dim 0 while its constant target shape says 1 there, and
     rewrites that 1 to 0 ("copy dim 0 from the input"); repeated until nothing
     changes, since each fix lets the batch reach the next Reshape downstream;
  3. audits every other node that could pin or mix the batch axis (Expand, Tile,
     ConstantOfShape, Resize, Slice, Split, Concat, Transpose, ... and constants with
     a leading 1 that are broadcast against batch tensors) and fails on anything it
     cannot prove batch-safe;
  4. drops the old value_info, re-runs strict shape inference and the full
     onnx.checker, and writes the model. Weights and all other nodes are untouched.

With --check it runs ONNX Runtime (CPU) on 8 frames (two real photos letterboxed as
the server does, two variants of them, four seeded synthetic ones) through the
ORIGINAL model one frame at a time and through the converted model at batch 1, 4
and 8, and fails unless every output of every frame agrees within --tol.
With --bench it prints a Markdown table of CPU latency per frame at batch 1, 4, 8.

Usage:
  .deps/onnx-tools/bin/python deploy/make-batched-model.py IN.onnx [OUT.onnx|OUT_DIR/]
      [--check] [--bench] [--images DIR] [--threads 2] [--bench-runs 7] [--tol 1e-4]
  OUT defaults to .deps/models/<IN stem>_batch.onnx (a directory gets the same name).
  Exit status: 0 ok, 1 conversion refused or outputs differ, 2 usage error.

Checked with (pinned in deploy/onnx-tools-requirements.txt):
  Python 3.11.7, onnx 1.23.2, onnxruntime 1.31.1, numpy 2.4.6, pillow 13.0.0,
  protobuf 7.36.2, ml_dtypes 0.7.0.
The models are AGPL-3.0 (Ultralytics): never commit them or the converted files;
they belong in the git-ignored .deps/models/.
"""

import argparse
import os
import statistics
import sys
import time

import numpy as np
import onnx
from onnx import numpy_helper, shape_inference

BATCH = "batch"  # name of the symbolic batch dimension

# Elementwise ops whose constant operands are broadcast against the data.
BROADCAST_OPS = {"Add", "Sub", "Mul", "Div", "Pow", "Max", "Min", "Sum", "Mean",
                 "Where", "Equal", "Less", "Greater", "And", "Or", "PRelu"}
# Ops with an axis attribute/input that must not be the batch axis (0).
AXIS_OPS = {"Concat", "Split", "Gather", "Softmax", "LogSoftmax", "Hardmax",
            "Flatten", "ArgMax", "ArgMin", "CumSum", "TopK"}
REDUCE_PREFIX = "Reduce"


class Refused(Exception):
    """The graph does something with the batch axis this script cannot fix."""


# --------------------------------------------------------------------------- helpers

def dims_of(value_info):
    """[int | str | None] for a ValueInfoProto, or None if it has no shape."""
    t = value_info.type.tensor_type
    if not t.HasField("shape"):
        return None
    out = []
    for d in t.shape.dim:
        if d.HasField("dim_value"):
            out.append(d.dim_value)
        elif d.HasField("dim_param"):
            out.append(d.dim_param)
        else:
            out.append(None)
    return out


def inferred_shapes(model, batch):
    """Map tensor name -> dims, inferred on a copy whose inputs have dim 0 = `batch`.

    Probing with concrete batch sizes rather than the symbol: ONNX shape inference
    turns a symbolic dim into an anonymous one at some ops (Resize with scales, for
    one), which would hide where the batch went.
    """
    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    del probe.graph.value_info[:]
    inits = {i.name for i in probe.graph.initializer}
    for inp in probe.graph.input:
        if inp.name not in inits:
            dim0 = inp.type.tensor_type.shape.dim[0]
            dim0.Clear()
            dim0.dim_value = batch
    for out in probe.graph.output:          # let inference find these itself
        out.type.tensor_type.ClearField("shape")
    probe = shape_inference.infer_shapes(probe, data_prop=True)
    g = probe.graph
    shapes = {}
    for vi in list(g.input) + list(g.value_info) + list(g.output):
        shapes[vi.name] = dims_of(vi)
    for init in g.initializer:
        shapes[init.name] = list(init.dims)
    return shapes


def batch_probe(model):
    """Return (carries_batch(name) predicate, shapes at probe batch 2, at 3).

    A tensor carries the batch in dim 0 iff its dim 0 follows the input's batch
    (2 with a batch-2 input, 3 with a batch-3 input).
    """
    at2, at3 = inferred_shapes(model, 2), inferred_shapes(model, 3)

    def carries_batch(name):
        a, b = at2.get(name), at3.get(name)
        return bool(a) and bool(b) and a[0] == 2 and b[0] == 3
    return carries_batch, at2, at3


def constants(graph):
    """Map name -> (numpy value, holder) for initializers and Constant nodes."""
    found = {}
    for init in graph.initializer:
        found[init.name] = (numpy_helper.to_array(init), init)
    for node in graph.node:
        if node.op_type == "Constant":
            for attr in node.attribute:
                if attr.name == "value":
                    found[node.output[0]] = (numpy_helper.to_array(attr.t), node)
    return found


def set_constant(graph, holder, name, value):
    """Overwrite a constant (initializer or Constant node) in place."""
    tensor = numpy_helper.from_array(value, name)
    if isinstance(holder, onnx.TensorProto):
        holder.CopyFrom(tensor)
    else:
        for attr in holder.attribute:
            if attr.name == "value":
                attr.t.CopyFrom(tensor)


def unique_name(graph, base):
    taken = {i.name for i in graph.initializer} | {o for n in graph.node for o in n.output}
    name, k = base, 1
    while name in taken:
        k += 1
        name = f"{base}_{k}"
    return name


def attr(node, name, default=None):
    for a in node.attribute:
        if a.name == name:
            return onnx.helper.get_attribute_value(a)
    return default


def describe(dims):
    if dims is None:
        return "(unknown)"
    return "[" + ",".join("?" if d is None else str(d) for d in dims) + "]"


# --------------------------------------------------------------------------- convert

def symbolic_io(model):
    """Name dim 0 of every real graph input and every output `batch`."""
    g = model.graph
    inits = {i.name for i in g.initializer}
    changed = []
    for vi in list(g.input) + list(g.output):
        if vi.name in inits:
            continue
        dims = vi.type.tensor_type.shape.dim
        if not dims:
            raise Refused(f"{vi.name}: no shape, cannot locate its batch axis")
        if not (dims[0].dim_value == 1 or dims[0].dim_param):
            raise Refused(f"{vi.name}: dim 0 is {dims[0].dim_value}, expected batch 1")
        before = describe(dims_of(vi))
        dims[0].Clear()
        dims[0].dim_param = BATCH
        changed.append(f"{'input ' if vi in g.input else 'output'} {vi.name}: "
                       f"{before} -> {describe(dims_of(vi))}")
    return changed


def fix_reshapes(model):
    """Rewrite leading-1 Reshape target shapes on batch-carrying data to 0.

    Returns the list of change descriptions. Iterates to a fixed point: a rewrite lets
    shape inference carry `batch` past that Reshape, which may expose the next one.
    """
    g = model.graph
    changes = []
    for _ in range(len(g.node) + 1):
        carries_batch, _, _ = batch_probe(model)
        consts = constants(g)
        todo = []  # (node index, new shape array)
        for index, node in enumerate(g.node):
            if node.op_type != "Reshape" or node.input[1] not in consts:
                continue
            target, _ = consts[node.input[1]]
            if not carries_batch(node.input[0]) or target.size == 0 or target[0] != 1:
                continue
            new = target.copy()
            if attr(node, "allowzero", 0) == 0:
                new[0] = 0                      # 0 = copy dim 0 (the batch) from the data
            elif -1 not in target.tolist():
                new[0] = -1                     # allowzero=1: infer it instead
            else:
                raise Refused(f"Reshape {node.name}: allowzero=1 and already has a -1")
            todo.append((index, new))
        if not todo:
            return changes
        # Rewrite a constant in place only if every node using it gets the same new
        # value; otherwise the rewritten Reshapes get a private copy.
        groups = {}  # (constant name, new value) -> [node index]
        for index, new in todo:
            key = (g.node[index].input[1], tuple(new.tolist()))
            groups.setdefault(key, []).append(index)
        users = {}
        for index, node in enumerate(g.node):
            for name in node.input:
                users.setdefault(name, set()).add(index)
        for (name, new), indices in groups.items():
            value, holder = consts[name]
            new = np.array(new, dtype=value.dtype)
            if users[name] == set(indices):
                set_constant(g, holder, name, new)
                target_name = name
            else:
                target_name = unique_name(g, name + "_batch")
                g.initializer.append(numpy_helper.from_array(new, target_name))
            for index in indices:
                node = g.node[index]
                node.input[1] = target_name
                changes.append(
                    f"Reshape {node.name}: shape {name} {value.tolist()} -> "
                    f"{target_name} {new.tolist()} (data dim 0 is the batch; "
                    f"{'0 = copy it from the input' if new[0] == 0 else '-1 = infer it'})")
    raise Refused("Reshape rewriting did not reach a fixed point")


def audit(model):
    """Check every node that could pin or mix the batch axis; return notes.

    Raises Refused for anything not provably batch-safe.
    """
    g = model.graph
    is_batch, shapes, _ = batch_probe(model)
    consts = constants(g)
    notes = []

    def const(i, node):
        """Value of the node's i-th input if it is a constant, else None."""
        if len(node.input) > i and node.input[i] in consts:
            return consts[node.input[i]][0]
        return None

    for node in g.node:
        op, name = node.op_type, node.name
        data_batch = bool(node.input) and is_batch(node.input[0])
        rank = len(shapes.get(node.input[0]) or []) if node.input else 0
        if op == "Reshape":
            target = const(1, node)
            if target is None:
                notes.append(f"ok  Reshape {name}: computed shape (follows the input)")
            elif data_batch and target.size and target[0] in (0, -1):
                notes.append(f"ok  Reshape {name}: shape {target.tolist()} keeps the batch")
            elif not data_batch:
                notes.append(f"ok  Reshape {name}: data has no batch axis")
            else:
                raise Refused(f"Reshape {name}: shape {target.tolist()} on batch data")
        elif op == "Expand":
            target = const(1, node)
            if data_batch and target is not None and target.size and target[0] != 1:
                raise Refused(f"Expand {name}: shape {target.tolist()} fixes the batch")
            notes.append(f"ok  Expand {name}: shape "
                         f"{'computed' if target is None else target.tolist()} "
                         "(a leading 1 broadcasts over the batch)")
        elif op == "Tile":
            reps = const(1, node)
            if data_batch and (reps is None or reps[0] != 1):
                raise Refused(f"Tile {name}: repeats the batch axis")
            notes.append(f"ok  Tile {name}: "
                         f"{'repeats[0] = 1' if data_batch else 'data has no batch axis'}")
        elif op == "ConstantOfShape":
            target = const(0, node)
            if target is not None and target.size and target[0] == 1:
                raise Refused(f"ConstantOfShape {name}: constant shape {target.tolist()} "
                              "(would need a Shape-derived batch)")
            notes.append(f"ok  ConstantOfShape {name}: shape not a batch-1 constant")
        elif op == "Resize":
            sizes, scales = const(3, node), const(2, node)
            if data_batch and sizes is not None and sizes.size:
                raise Refused(f"Resize {name}: constant sizes {sizes.tolist()} fix the batch")
            if data_batch and scales is not None and scales.size and scales[0] != 1:
                raise Refused(f"Resize {name}: scales the batch axis")
            notes.append(f"ok  Resize {name}: scales "
                         f"{None if scales is None else scales.tolist()} leave the batch alone")
        elif op == "Slice" and data_batch:
            axes = const(3, node)
            axes = list(range(rank)) if axes is None else [a % rank for a in axes.tolist()]
            if 0 in axes:
                raise Refused(f"Slice {name}: slices the batch axis")
            notes.append(f"ok  Slice {name}: axes {axes} (not the batch)")
        elif op == "Transpose" and data_batch:
            perm = attr(node, "perm")
            if perm is None or perm[0] != 0:
                raise Refused(f"Transpose {name}: moves the batch axis ({perm})")
            notes.append(f"ok  Transpose {name}: perm {list(perm)} keeps axis 0")
        elif (op in AXIS_OPS or op.startswith(REDUCE_PREFIX)) and data_batch:
            if op.startswith(REDUCE_PREFIX):
                axes = attr(node, "axes")
                if axes is None and const(1, node) is not None:
                    axes = const(1, node).tolist()
                axes = list(range(rank)) if not axes else [a % rank for a in axes]
            else:
                default = 0 if op in ("Concat", "Split", "Gather", "CumSum") else (
                    1 if op in ("Flatten",) else -1)
                axis = attr(node, "axis", default)
                if op == "CumSum":
                    axis = int(const(1, node)) if const(1, node) is not None else 0
                axes = [axis % rank]
            if 0 in axes:
                raise Refused(f"{op} {name}: works across the batch axis")
            if op not in ("Concat", "Split"):   # too many of those to list one by one
                notes.append(f"ok  {op} {name}: axis {axes} (not the batch)")
        elif op in BROADCAST_OPS:
            out_rank = len(shapes.get(node.output[0]) or [])
            for inp in node.input:
                if inp in consts and consts[inp][0].ndim == out_rank and out_rank > 1:
                    value = consts[inp][0]
                    if value.shape[0] != 1 and is_batch(node.output[0]):
                        raise Refused(f"{op} {name}: constant {inp} {list(value.shape)} "
                                      "has a fixed batch")
                    notes.append(f"ok  {op} {name}: constant {inp} {list(value.shape)} "
                                 "broadcasts over the batch")
                elif inp in consts and consts[inp][0].ndim > 1:
                    notes.append(f"ok  {op} {name}: constant {inp} "
                                 f"{list(consts[inp][0].shape)} has no batch axis")
    concat_split = sum(1 for n in g.node if n.op_type in ("Concat", "Split"))
    notes.append(f"ok  {concat_split} Concat/Split nodes: none joins or splits along the batch axis")
    return notes


def convert(src, dst):
    model = onnx.load(src)
    orig_outputs = {o.name: dims_of(o) for o in model.graph.output}
    print(f"== converting {src}")
    print(f"   opset {[(o.domain or 'ai.onnx', o.version) for o in model.opset_import]}, "
          f"IR {model.ir_version}, {len(model.graph.node)} nodes, "
          f"{len(model.graph.value_info)} value_info entries (dropped)")
    changes = symbolic_io(model)
    del model.graph.value_info[:]             # stale batch-1 shapes
    changes += fix_reshapes(model)
    notes = audit(model)

    # Every output must now follow the input batch, other dims unchanged.
    _, at2, at3 = batch_probe(model)
    for out in model.graph.output:
        for probe, shapes in ((2, at2), (3, at3)):
            want = [probe] + orig_outputs[out.name][1:]
            if shapes[out.name] != want:
                raise Refused(f"output {out.name}: inferred {describe(shapes[out.name])} "
                              f"for an input batch of {probe}, expected {describe(want)}")
    # Strict inference (declared `batch` shapes must not contradict the graph) and the
    # full checker. The inferred value_info is not kept: ORT infers its own, and the
    # intermediate shapes would only carry anonymous dims (unk__N) after Resize.
    shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)
    onnx.checker.check_model(model, full_check=True)
    meta = {p.key: p for p in model.metadata_props}
    entry = meta.get("batch_dim") or model.metadata_props.add()
    entry.key, entry.value = "batch_dim", (
        f"symbolic '{BATCH}' (deploy/make-batched-model.py from {os.path.basename(src)})")

    print("   changed:")
    for c in changes:
        print(f"     {c}")
    print("   inspected, left as is:")
    for n in notes:
        print(f"     {n}")
    os.makedirs(os.path.dirname(os.path.abspath(dst)), exist_ok=True)
    onnx.save(model, dst)
    print(f"   wrote {dst} ({os.path.getsize(dst)} bytes)")
    for vi in list(model.graph.input) + list(model.graph.output):
        kind = "input " if vi in model.graph.input else "output"
        print(f"   {kind} {vi.name}: {describe(dims_of(vi))}")


# --------------------------------------------------------------------------- check

def letterbox(path, size):
    """RGB image -> f32 [3,S,S] in 0..1, letterboxed as MODELS.md describes."""
    from PIL import Image
    img = Image.open(path).convert("RGB")
    w, h = img.size
    r = min(size / h, size / w)
    nw, nh = round(w * r), round(h * r)
    img = img.resize((nw, nh), Image.BILINEAR)
    canvas = np.full((size, size, 3), 114, np.uint8)
    top, left = (size - nh) // 2, (size - nw) // 2
    canvas[top:top + nh, left:left + nw] = np.asarray(img)
    return canvas.astype(np.float32).transpose(2, 0, 1) / 255.0


def test_frames(size, image_dir):
    """8 distinct frames [8,3,S,S]: photos, variants of them, seeded synthetic ones."""
    rng = np.random.default_rng(20260402)
    frames, labels = [], []
    photos = [os.path.join(image_dir, n) for n in ("bus.jpg", "astronaut.png")]
    try:
        real = [letterbox(p, size) for p in photos]
        frames += [real[0], real[1], real[0][:, :, ::-1].copy(), real[1] * 0.6]
        labels += ["bus.jpg", "astronaut.png", "bus.jpg mirrored", "astronaut.png x0.6"]
    except (ImportError, OSError) as err:
        print(f"   note: no real photos ({err}); using synthetic frames only")
    blocks = rng.random((3, size // 16, size // 16), dtype=np.float32)
    synthetic = [
        ("uniform noise", rng.random((3, size, size), dtype=np.float32)),
        ("16px block noise", np.repeat(np.repeat(blocks, 16, 1), 16, 2)),
        ("gray 114 + noise", np.clip(114 / 255 + 0.05 * rng.standard_normal(
            (3, size, size), dtype=np.float32), 0, 1)),
        ("clipped gaussian", np.clip(0.5 + 0.25 * rng.standard_normal(
            (3, size, size), dtype=np.float32), 0, 1)),
        ("horizontal ramp", np.broadcast_to(np.linspace(0, 1, size, dtype=np.float32),
                                            (3, size, size)).copy()),
        ("uniform noise 2", rng.random((3, size, size), dtype=np.float32)),
    ]
    for label, frame in synthetic[:8 - len(frames)]:
        frames.append(frame)
        labels.append(label)
    return np.ascontiguousarray(np.stack(frames).astype(np.float32)), labels


def session(path, threads):
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])


def check(src, dst, image_dir, threads, tol):
    import onnxruntime as ort
    ref_sess, new_sess = session(src, threads), session(dst, threads)
    inp = new_sess.get_inputs()[0]
    size = inp.shape[2]
    print(f"== check {os.path.basename(dst)} against {os.path.basename(src)} "
          f"(onnxruntime {ort.__version__}, CPU, {threads} threads, tol {tol:g})")
    for io in list(new_sess.get_inputs()) + list(new_sess.get_outputs()):
        print(f"   ort sees {io.name}: {io.shape} {io.type}")
        if io.shape[0] != BATCH:
            print(f"FAIL: {io.name} dim 0 is {io.shape[0]!r}, not '{BATCH}'", file=sys.stderr)
            return False
    frames, labels = test_frames(size, image_dir)
    print(f"   frames: {', '.join(labels)}")
    names = [o.name for o in new_sess.get_outputs()]
    ref = [ref_sess.run(names, {inp.name: frames[i:i + 1]}) for i in range(len(frames))]
    ok = True
    print("   | batch | " + " | ".join(f"max abs diff {n}" for n in names) + " |")
    print("   |---|" + "---|" * len(names))
    for batch in (1, 4, 8):
        worst = [0.0] * len(names)
        for start in range(0, len(frames), batch):
            outs = new_sess.run(names, {inp.name: frames[start:start + batch]})
            for k, out in enumerate(outs):
                if out.shape[0] != batch or out.shape[1:] != ref[start][k].shape[1:]:
                    print(f"FAIL: {names[k]} shape {out.shape} at batch {batch}",
                          file=sys.stderr)
                    return False
                for j in range(batch):
                    diff = float(np.max(np.abs(out[j] - ref[start + j][k][0])))
                    worst[k] = max(worst[k], diff)
        print(f"   | {batch} | " + " | ".join(f"{w:.3g}" for w in worst) + " |")
        ok &= all(w <= tol for w in worst)
    # Sanity: the photo frames still detect something (the comparison would also
    # pass for a model that outputs garbage identically).
    scores = ref[0][0][0, 4:84]                 # [80 classes, N anchors]
    best_class = int(np.unravel_index(scores.argmax(), scores.shape)[0])
    print(f"   frame 0 ({labels[0]}): best score {scores.max():.2f}, class {best_class}")
    print("   check " + ("passed" if ok else "FAILED"))
    return ok


def bench(src, dst, threads, runs):
    ref_sess, new_sess = session(src, threads), session(dst, threads)
    inp = new_sess.get_inputs()[0]
    size = inp.shape[2]
    frames = np.random.default_rng(1).random((8, 3, size, size), dtype=np.float32)
    rows = []
    for label, sess, batch in (("original", ref_sess, 1), ("batched", new_sess, 1),
                               ("batched", new_sess, 4), ("batched", new_sess, 8)):
        feed = {inp.name: frames[:batch]}
        for _ in range(2):                     # warm-up
            sess.run(None, feed)
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            sess.run(None, feed)
            times.append((time.perf_counter() - t0) * 1000)
        med = statistics.median(times)
        rows.append((label, batch, med, min(times), med / batch))
    print(f"== CPU latency, {os.path.basename(dst)} ({threads} intra-op threads, "
          f"2 warm-up runs, median and min of {runs})")
    print("| model | S | batch | ms per run (median / min) | ms per frame (median) | frames/s |")
    print("|---|---|---|---|---|---|")
    for label, batch, med, mn, per in rows:
        print(f"| {label} | {size} | {batch} | {med:.1f} / {mn:.1f} | {per:.1f} | "
              f"{1000 / per:.0f} |")


# --------------------------------------------------------------------------- main

def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", help="batch-1 ONNX model")
    p.add_argument("dst", nargs="?", default=".deps/models/",
                   help="output file, or directory for <stem>_batch.onnx "
                        "(default .deps/models/)")
    p.add_argument("--check", action="store_true",
                   help="compare outputs with the original at batch 1, 4, 8")
    p.add_argument("--bench", action="store_true", help="time batch 1, 4, 8 on CPU")
    p.add_argument("--images", help="folder with bus.jpg and astronaut.png "
                                    "(default: images/ next to the input model)")
    p.add_argument("--threads", type=int, default=2, help="ORT intra-op threads (2)")
    p.add_argument("--bench-runs", type=int, default=7, help="timed runs per case (7)")
    p.add_argument("--tol", type=float, default=1e-4, help="max abs diff allowed (1e-4)")
    args = p.parse_args()

    dst = args.dst
    if dst.endswith(os.sep) or os.path.isdir(dst):
        stem = os.path.splitext(os.path.basename(args.src))[0]
        dst = os.path.join(dst, f"{stem}_batch.onnx")
    if os.path.abspath(dst) == os.path.abspath(args.src):
        p.error("output would overwrite the input")
    try:
        convert(args.src, dst)
    except Refused as err:
        print(f"FAIL: cannot make the batch symbolic: {err}", file=sys.stderr)
        return 1
    if args.check:
        image_dir = args.images or os.path.join(os.path.dirname(os.path.abspath(args.src)),
                                                "images")
        if not check(args.src, dst, image_dir, args.threads, args.tol):
            print(f"FAIL: {dst} does not reproduce {args.src}", file=sys.stderr)
            return 1
    if args.bench:
        bench(args.src, dst, args.threads, max(5, args.bench_runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
