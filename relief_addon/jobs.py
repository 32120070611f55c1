"""Long backend work from operators: synchronous in execute(), threaded in invoke().

An operator using `JobOperator` splits its work into three steps:

    prepare(context) -> payload      main thread: read bpy properties into plain Python values
    work(payload, progress[, cancel]) -> res   any thread: backend calls only, no bpy (static method);
                                     the backend's jobs (`relief_bsdf.jobs`), given `cancel`, a CancelToken
    finish(context, res)             main thread: create or change bpy data, report

`execute()` runs the three in a row (background mode, scripts, tests: no event loop there,
timers never fire).  `invoke()` runs `work` on a worker thread and polls it from a modal
timer, showing `wm.progress_*` and the task label in the status bar; Esc sets a flag that
the progress callback turns into `relief_bsdf.progress.Cancelled` at the next task boundary, and
a `work` that takes `cancel` gets it as the job's `relief_bsdf.jobs.CancelToken` (checked between
the job's stages too).
Every error becomes a Blender report (one line); a traceback goes to the console only for an internal
error (not bad input) or when Blender runs with --debug.  Every warning the work raises becomes one
report line `relief: warning: ...`, once per message (`relief_bsdf.errors.warning_line`, as the CLI
prints them), and the last one shows in the panel's status.
The work runs inside `workers.running_backend`: the preferences' worker count in force and
worker processes that start from the add-on's code, never from the user's script.
"""
from __future__ import annotations

import contextlib
import contextvars
import threading
import traceback
import warnings

import bpy


def _error_text(exc: BaseException) -> str:
    try:
        from relief_bsdf.errors import InputError
    except ImportError:            # pragma: no cover - backend missing entirely
        InputError = ()            # noqa: N806
    if InputError and isinstance(exc, InputError):
        return exc.one_line()
    return f"{type(exc).__name__}: {exc}"


def _print_trace(exc: BaseException, trace: str | None = None) -> None:
    """The traceback on the console: for an internal error, or any error under Blender's --debug."""
    try:
        from relief_bsdf.errors import InputError
    except ImportError:            # pragma: no cover
        InputError = ()            # noqa: N806
    if bpy.app.debug or not (InputError and isinstance(exc, InputError)):
        if trace is not None:
            print(trace)
        else:
            traceback.print_exception(exc)


@contextlib.contextmanager
def collected_warnings(into: list):
    """Within the block, warnings are not printed but collected into `into` as their one-line text, each
    message once (the operator reports them when the work is done)."""
    from relief_bsdf.errors import warning_line
    with warnings.catch_warnings():
        warnings.simplefilter("always")

        def keep(message, category, filename, lineno, file=None, line=None):
            text = warning_line(message, category)
            if text not in into:
                into.append(text)
        warnings.showwarning = keep
        yield into


class JobOperator:
    """Mixin for bpy.types.Operator subclasses (see module doc)."""

    job_label = "Relief"

    # ----------------------------------------------------------- to override
    def prepare(self, context):
        return None

    @staticmethod
    def work(payload, progress):
        raise NotImplementedError

    @classmethod
    def _run_work(cls, payload, progress, cancel=None):
        """`work(payload, progress)`, with `cancel=` (a relief_bsdf.jobs.CancelToken) where it takes one."""
        import inspect
        if cancel is not None and "cancel" in inspect.signature(cls.work).parameters:
            return cls.work(payload, progress, cancel=cancel)
        return cls.work(payload, progress)

    def finish(self, context, result) -> None:
        pass

    # ----------------------------------------------------------- synchronous
    def execute(self, context):
        said: list = []
        try:
            payload = self.prepare(context)
            # synchronous runs (blender --background, scripts): progress as log lines on stderr
            from relief_bsdf.progress import TerminalBar
            from .prefs import get_prefs
            from .workers import running_backend
            with running_backend(get_prefs(context).workers), collected_warnings(said):
                result = type(self)._run_work(payload, TerminalBar(self.job_label))
            self._report_warnings(context, said)
            self.finish(context, result)
        except Exception as exc:  # noqa: BLE001 - every failure becomes a report
            self._report_warnings(context, said)
            _print_trace(exc)
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(exc)}")
            return {"CANCELLED"}
        return {"FINISHED"}

    def _report_warnings(self, context, lines: list) -> None:
        for text in lines:
            self.report({"WARNING"}, text)
        if lines:
            _set_status(context, lines[-1])

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
            _print_trace(exc)
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(exc)}")
            return {"CANCELLED"}
        self._state = {"done": 0, "total": 1, "what": "", "result": None, "error": None, "finished": False,
                       "warnings": []}
        self._cancel = threading.Event()
        state, cancel, run_work = self._state, self._cancel, type(self)._run_work
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
                with running_backend(n_workers), collected_warnings(state["warnings"]):
                    from relief_bsdf.jobs import CancelToken
                    state["result"] = run_work(payload, progress, CancelToken(cancel))
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
        self._report_warnings(context, st["warnings"])
        err = st["error"]
        if err is not None:
            from relief_bsdf.progress import Cancelled
            if isinstance(err, Cancelled):
                self.report({"WARNING"}, f"{self.job_label}: cancelled")
                _set_status(context, f"{self.job_label}: cancelled")
                return {"CANCELLED"}
            _print_trace(err, st.get("trace", ""))
            self.report({"ERROR"}, f"{self.job_label}: {_error_text(err)}")
            _set_status(context, f"{self.job_label}: failed")
            return {"CANCELLED"}
        try:
            self.finish(context, st["result"])
        except Exception as exc:  # noqa: BLE001
            _print_trace(exc)
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
