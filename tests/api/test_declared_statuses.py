"""Every route's OpenAPI responses declare each problem status the route can raise.

The statuses are read from the code: every ``Problem(<status>, ...)`` in the route's function, in its
dependencies (FastAPI's dependency tree: the key's checks, the ``Existing*`` lookups) and, transitively, in
every function of the ``api`` package that these name (helpers called, or passed on as ``respond_once`` and
``start_job`` are). The application's exception handlers add what any route can answer: 422 for a request
FastAPI rejects or an ``InputError``, 503 for a database that is down or a full store.
"""

import ast
import importlib
import inspect
import pkgutil
import textwrap
import types

import pytest
from fastapi.routing import APIRoute

from api.problems import Problem

ANY_ROUTE = {422, 503}  # api/problems.py: validation and InputError; DBAPIError and a full disk


def _api_functions_named(function: types.FunctionType, tree: ast.AST):
    """The functions of the api package that ``function``'s code names (called or passed on)."""
    scope = {**function.__globals__, **_closure(function)}
    for node in ast.walk(tree):
        value = None
        if isinstance(node, ast.Name):
            value = scope.get(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            value = getattr(scope.get(node.value.id), node.attr, None)
        value = inspect.unwrap(value) if callable(value) else value
        if isinstance(value, types.FunctionType) and value.__module__.startswith("api."):
            yield value


def _closure(function: types.FunctionType) -> dict:
    return {name: cell.cell_contents for name, cell in zip(function.__code__.co_freevars, function.__closure__ or ())}


def raised_statuses(function: types.FunctionType, seen: set | None = None) -> set[int]:
    """The statuses of the ``Problem`` s that ``function`` and the api functions it names can raise."""
    seen = set() if seen is None else seen
    if function in seen:
        return set()
    seen.add(function)
    tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
    statuses = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                function.__globals__.get(node.func.id) is Problem:
            status = node.args[0]
            assert isinstance(status, ast.Constant) and isinstance(status.value, int), (
                f"{function.__qualname__}: a Problem's status must be a literal for this test to read it")
            statuses.add(status.value)
    for callee in _api_functions_named(function, tree):
        statuses |= raised_statuses(callee, seen)
    return statuses


def _dependency_calls(dependant):
    for dependency in dependant.dependencies:
        if dependency.call is not None:
            yield dependency.call
        yield from _dependency_calls(dependency)


def _routes():
    """Every route of the routers in ``api.routers`` (the app includes each under its prefix)."""
    import api.routers

    modules = [importlib.import_module(f"api.routers.{module.name}")
               for module in pkgutil.iter_modules(api.routers.__path__)]
    return [route for module in modules for route in module.router.routes if isinstance(route, APIRoute)]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from services.db.engine import make_engine, make_sessions
    from services.jobs.queue import JobQueue, job_broker
    from services.jobs.tracker import JobTracker
    from services.runtime import Runtime
    from services.settings import Settings
    from services.storage.artifacts import ArtifactStore

    from api.app import create_app

    directory = tmp_path_factory.mktemp("declared")
    settings = Settings(data_dir=directory, broker_url="", mqtt_host="")
    engine = make_engine(f"sqlite:///{directory / 'service.db'}")
    sessions = make_sessions(engine)
    runtime = Runtime(settings, engine, sessions, ArtifactStore(directory / "artifacts"), JobTracker(sessions))
    return create_app(runtime, JobQueue(job_broker(settings), settings.job_queue))


def test_every_problem_a_route_raises_is_declared(app):
    # operation ids are the routes' names (api/app.py)
    operations = {operation["operationId"]: (f"{method.upper()} {path}", operation["responses"])
                  for path, item in app.openapi()["paths"].items() for method, operation in item.items()}
    routes = _routes()
    assert sorted(route.name for route in routes) == sorted(operations)
    undeclared = {}
    for route in routes:
        label, responses = operations[route.name]
        functions = [inspect.unwrap(function) for function in [route.endpoint, *_dependency_calls(route.dependant)]]
        raised = set().union(*(raised_statuses(function) for function in functions
                               if isinstance(function, types.FunctionType)))
        if label.split()[1].startswith("/v1/"):
            raised |= ANY_ROUTE
        if raised - {int(status) for status in responses}:
            undeclared[label] = sorted(raised - {int(status) for status in responses})
    assert not undeclared


def test_the_reader_sees_the_problems_of_the_code():
    """The reading itself: a route's own Problem, its helpers', and one passed on without being called."""
    from api.routers import calibrations, scans

    assert raised_statuses(scans.create_scan) >= {409, 422, 503}  # _calibration_for, _part_type_for, start_job
    assert 413 in raised_statuses(calibrations.create_calibration_set)  # read_limited, called
    assert 422 in raised_statuses(calibrations.create_calibration_set)  # respond_once (passed on) -> replay
    assert raised_statuses(scans._existing_scan) == {404}
