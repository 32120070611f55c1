"""Long backend work from operators: synchronous in execute(), threaded in invoke().

An operator using `JobOperator` splits its work into three steps:

    prepare(context) -> payload      main thread: read bpy properties into plain Python values
    work(payload, progress) -> res   any thread: backend calls only, no bpy (static method)
    finish(context, res)             main thread: create or change bpy data, report

`execute()` runs the three in a row (background mode, scripts, tests: no event loop there,
timers never fire).  `invoke()` runs `work` on a worker thread and polls it from a modal
timer, showing `wm.progress_*` and the task label in the status bar; Esc sets a flag that
the progress callback turns into `relief_bsdf.progress.Cancelled` at the next task boundary.
Every error becomes a Blender report (one line); the traceback goes to the console too.
The work runs inside `workers.running_backend`: the preferences' worker count in force and
worker processes that start from the add-on's code, never from the user's script.
"""
from __future__ import annotations

import contextvars
import threading
import traceback

import bpy


def _error_text(exc: BaseException) -> str:
    try:
        from relief_bsdf.errors import InputError
    except ImportError:            # pragma: no cover - backend missing entirely
        InputError = ()            # noqa: N806
    if InputError and isinstance(exc, InputError):
        return exc.one_line()
    return f"{type(exc).__name__}: {exc}"


class JobOperator:
    """Mixin for bpy.types.Operator subclasses (see module doc)."""

    job_label = "Relief"

    # ----------------------------------------------------------- to override
    def prepare(self, context):
        return None

    @staticmethod
    def work(payload, progress):
        raise NotImplementedError

    def finish(self, context, result) -> None:
        pass

    # ----------------------------------------------------------- synchronous
    def execute(self, context):
        try:
            payload = self.prepare(context)
            # synchronous runs (blender --background, scripts): progress as log lines on stderr
            from relief_bsdf.progress import TerminalBar
            from .prefs import get_prefs
            from .workers import running_backend
            with running_backend(get_prefs(context).workers):
                result = type(self).work(payload, TerminalBar(self.job_label))
            self.finish(context, result)
        except Exception as exc:  # noqa: BLE001 - every failure becomes a report
            traceback.print_exc()
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(exc)}")
            return {"CANCELLED"}
        return {"FINISHED"}

    # ----------------------------------------------------------- threaded
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        return self.invoke_threaded(context)

    def invoke_threaded(self, context):
        """Start `work` on a worker thread; `modal` polls it (see module doc)."""
        try:
            payload = self.prepare(context)
        except Exception as exc:  # noqa: BLE001
            traceback.print_exc()
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(exc)}")
            return {"CANCELLED"}
        self._state = {"done": 0, "total": 1, "what": "", "result": None, "error": None, "finished": False}
        self._cancel = threading.Event()
        state, cancel, work = self._state, self._cancel, type(self).work
        from .prefs import get_prefs
        from .workers import running_backend
        n_workers = get_prefs(context).workers

        def progress(done, total, what=""):
            state["done"], state["total"], state["what"] = done, max(total, 1), what
            if cancel.is_set():
                from relief_bsdf.progress import Cancelled
                raise Cancelled("cancelled by the user")

        def run():
            try:
                with running_backend(n_workers):
                    state["result"] = work(payload, progress)
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread
                state["error"] = exc
                state["trace"] = traceback.format_exc()
            finally:
                state["finished"] = True

        # the worker thread runs in a copy of this thread's context, so parallel settings in force
        # here (`relief_bsdf.parallel.parallel_settings`, a ContextVar) reach the backend's map_tasks
        ctx = contextvars.copy_context()
        self._thread = threading.Thread(target=ctx.run, args=(run,), name=f"relief-{self.bl_idname}", daemon=True)
        wm = context.window_manager
        wm.progress_begin(0, 1000)
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        self._thread.start()
        _set_status(context, f"{self.job_label}: started (Esc cancels)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._cancel.set()
            _set_status(context, f"{self.job_label}: cancelling at the next task boundary...")
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        st = self._state
        wm = context.window_manager
        wm.progress_update(int(1000 * st["done"] / st["total"]))
        _set_status(context, f"{self.job_label}: {st['done']}/{st['total']} {st['what']}")
        if not st["finished"]:
            return {"PASS_THROUGH"}
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        self._thread.join()
        err = st["error"]
        if err is not None:
            from relief_bsdf.progress import Cancelled
            if isinstance(err, Cancelled):
                self.report({"WARNING"}, f"{self.job_label}: cancelled")
                _set_status(context, f"{self.job_label}: cancelled")
                return {"CANCELLED"}
            print(st.get("trace", ""))
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(err)}")
            _set_status(context, f"{self.job_label}: failed")
            return {"CANCELLED"}
        try:
            self.finish(context, st["result"])
        except Exception as exc:  # noqa: BLE001
            traceback.print_exc()
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(exc)}")
            _set_status(context, f"{self.job_label}: failed")
            return {"CANCELLED"}
        _set_status(context, f"{self.job_label}: done")
        return {"FINISHED"}


def _set_status(context, text: str) -> None:
    props = getattr(context.scene, "relief", None)
    if props is not None:
        props.job_status = text
    if context.workspace is not None:
        context.workspace.status_text_set(text if not text.endswith(("done", "failed", "cancelled")) else None)
    for area in getattr(context.screen, "areas", ()):
        if area.type == "VIEW_3D":
            area.tag_redraw()
