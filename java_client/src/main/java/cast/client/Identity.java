package cast.client;

/**
 * Who a component is, as its token states it: its id, its own subarchitecture,
 * and whether it may write every subarchitecture. Identity comes only from the
 * token, which the server verifies on every call.
 *
 * @param componentId the component's id
 * @param subarchitecture its own SA
 * @param privileged whether it may write every SA
 */
public record Identity(String componentId, String subarchitecture, boolean privileged) {}
